"""How much of a calibration's error is the model's own, not noise (issue 18, item 5: a sigma that includes model
error).

For each random truth of lrfsim.testing.random_scenarios.random_scenario_wide(seed, broad=True), the same recording is
simulated twice, once as shipped and once without range noise and with an exact tape (sigma 1 um). Both are
calibrated as shipped. An error that the noise-free, exact-map recording reproduces is the model's: noise
cannot make it, and the reported sigma, which is noise's, does not cover it. Prints per truth and recording
the DH errors in units of the reported sigma.

Seeds 28 and 67 (tilted spins) were the two largest alpha errors of
``bench_trust.py --broad --seeds 120`` (-3.3 sigma each); 6 and 12 are along the motor axis, for comparison.

With ``--per-marker``, per truth also the marker model's residuals AT THE TRUTH (the noise-free marker returns
and true marker positions of ``lrfsim plan``): per marker the mean whitened range, in-plane and across-plane
lateral residual, with the standard error of each mean over the marker's scan lines. The model takes every
return's residual as independent noise of mean 0; a mean many standard errors from 0 is a per-marker model error
(near perpendicular truth 5: the across-plane part, up to 12 standard errors on one marker; docs/study.md).

    python benchmarks/bench_model_error.py [--seeds 28 67 6 12] [--per-marker]
"""

from __future__ import annotations

import argparse
import math
import tempfile
import time
from pathlib import Path

from lrfcal.model.kinematics import DH_NAMES
from lrfsim.scenario.file import Scenario
from lrfsim.simulation.recording import write_recording
from lrfsim.simulation.simulate import simulate
from lrfsim.testing.random_scenarios import alpha_kind_of, random_scenario_wide
from lrfsim.trials.trial import calibrate_recording

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


def per_marker(scenario: Scenario) -> list[str]:
    """Lines of the per-marker mean whitened residuals at the truth (module docstring)."""
    import numpy as np

    from lrfcal.estimate.information import model_residuals
    from lrfcal.model.kinematics import beam_rays_W
    from lrfcal.model.marker import MarkerSensor
    from lrfsim.plan.prediction import marker_observations

    obs, markers_W, params, _, _, _ = marker_observations(scenario)
    assert scenario.markers is not None
    sensor = MarkerSensor.of("sphere", float(scenario.markers.radius_m), float(scenario.sensor.divergence_rad))
    res, _ = model_residuals(params, obs, markers_W, sensor=sensor)
    res = res.reshape(-1, 4)  # range, then the lateral residual in W
    _, d = beam_rays_W(params, obs.lambda_rad, obs.mu_rad + 0.5 * math.pi)  # in the scan plane, across the beam
    _, d0 = beam_rays_W(params, obs.lambda_rad, obs.mu_rad)
    n = np.cross(d0, d)  # the scan plane's normal
    parts = {"range": res[:, 0], "in-plane": (res[:, 1:] * d).sum(1), "across": (res[:, 1:] * n).sum(1)}
    out = []
    for m in np.unique(obs.marker):
        k = obs.marker == m
        lines = max(np.unique(obs.scan[k]).size, 1)
        se = {name: v[k].std() / math.sqrt(lines) for name, v in parts.items()}
        cells = [f"{name} {v[k].mean():+.2f}" + (f" ({v[k].mean() / se[name]:+.1f} se)" if lines > 1 and se[name] > 0
                                                 else "") for name, v in parts.items()]
        out.append(f"    marker {m:2d}: {int(k.sum()):4d} returns on {lines:3d} lines; " + ", ".join(cells))
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--seeds", type=int, nargs="+", default=[28, 67, 6, 12])
    ap.add_argument("--per-marker", action="store_true", help="also the residuals at the truth, per marker")
    args = ap.parse_args()
    t0 = time.perf_counter()
    with tempfile.TemporaryDirectory() as tmp:
        for seed in args.seeds:
            sc = random_scenario_wide(seed, broad=True)
            exact = sc.model_copy(update={"tape": sc.tape.model_copy(update={"sigma_m": EXACT_TAPE_M})})
            print(f"seed {seed} ({alpha_kind_of(sc)}, alpha {math.degrees(sc.rig.dh.alpha):+.2f} deg):", flush=True)
            print(f"  as shipped:            {_row(sc, True, Path(tmp) / f'{seed}_noisy')}", flush=True)
            print(f"  no noise, exact tape:  {_row(exact, False, Path(tmp) / f'{seed}_exact')}", flush=True)
            if args.per_marker:
                print("  at the truth, mean whitened residual per marker (standard errors over its lines):")
                print("\n".join(per_marker(exact)), flush=True)
    print(f"benchmark wall time {time.perf_counter() - t0:.0f} s")


if __name__ == "__main__":
    main()
