"""How much of a calibration's error is the model's own, not noise (issue 18, item 5: a sigma that includes model
error).

For each random truth of lrfsim.randomize.random_scenario_wide(seed, broad=True), the same recording is
simulated twice, once as shipped and once without range noise and with an exact tape (sigma 1 um). Both are
calibrated as shipped. An error that the noise-free, exact-map recording reproduces is the model's: noise
cannot make it, and the reported sigma, which is noise's, does not cover it. Prints per truth and recording
the DH errors in units of the reported sigma.

Seeds 28 and 67 (tilted spins) were the two largest alpha errors of
``bench_trust.py --broad --seeds 120`` (-3.3 sigma each); 6 and 12 are along the motor axis, for comparison.

    python benchmarks/bench_model_error.py [--seeds 28 67 6 12]
"""

from __future__ import annotations

import argparse
import math
import tempfile
import time
from pathlib import Path

from lrfcal.model.kinematics import DH_NAMES
from lrfsim.randomize import alpha_kind_of, random_scenario_wide
from lrfsim.recording import write_recording
from lrfsim.scenario import Scenario
from lrfsim.simulate import simulate
from lrfsim.trial import calibrate_recording

#: the tape's sigma of the "exact" map [m]
EXACT_TAPE_M = 1e-6


def _row(scenario: Scenario, noise: bool, folder: Path) -> str:
    write_recording(simulate(scenario, noise=noise), scenario, folder)
    trial = calibrate_recording(folder)
    if trial.status != "calibrated":
        return f"refused: {trial.reason[:100]}"
    parts = []
    for name, e, s, z in zip(DH_NAMES, trial.errors, trial.sigma, trial.z, strict=True):
        scale, unit = (math.degrees(1.0), "deg") if name in ("alpha", "beta") else (1000.0, "mm")
        parts.append(f"{name} {e * scale:+.3f} +- {s * scale:.3f} {unit} ({z:+.1f})")
    return ", ".join(parts)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--seeds", type=int, nargs="+", default=[28, 67, 6, 12])
    args = ap.parse_args()
    t0 = time.perf_counter()
    with tempfile.TemporaryDirectory() as tmp:
        for seed in args.seeds:
            sc = random_scenario_wide(seed, broad=True)
            exact = sc.model_copy(update={"tape": sc.tape.model_copy(update={"sigma_m": EXACT_TAPE_M})})
            print(f"seed {seed} ({alpha_kind_of(sc)}, alpha {math.degrees(sc.rig.dh.alpha):+.2f} deg):", flush=True)
            print(f"  as shipped:            {_row(sc, True, Path(tmp) / f'{seed}_noisy')}", flush=True)
            print(f"  no noise, exact tape:  {_row(exact, False, Path(tmp) / f'{seed}_exact')}", flush=True)
    print(f"benchmark wall time {time.perf_counter() - t0:.0f} s")


if __name__ == "__main__":
    main()
