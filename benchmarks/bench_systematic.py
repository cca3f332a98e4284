"""What each systematic range error costs a calibration that does not model it (issue 12).

Runs tunnel_v (and plane_30deg) through lrfsim.trial with each effect of ``sensor.systematic`` switched on in
turn, at the assumed magnitudes of docs/sensor_errors.md (no published UTM-30LX-EW figure was verified: these
are of the order of the spec's +-30 mm accuracy, not measurements), then all together, and multi-echo returns
read from /echoes (strongest echo) instead of /scan. Prints per case the DH errors, the reported sigma and the
largest |error| / sigma: a case beyond 4 sigma is a confident wrong result the bias causes.

    python benchmarks/bench_systematic.py [--scenarios tunnel_v plane_30deg]
"""

from __future__ import annotations

import argparse
import copy
import math
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import yaml

from lrfcal.kinematics import DH_NAMES
from lrfsim.scenario import parse_scenario
from lrfsim.trial import CONFIDENT_WRONG_Z, Trial, calibrate_recording, record

ROOT = Path(__file__).resolve().parents[1]

#: case -> changes to ``sensor`` (assumed magnitudes: docs/sensor_errors.md)
CASES: dict[str, dict[str, object]] = {
    "none (idealised)": {},
    "offset +10 mm": {"systematic": {"range_offset_m": 0.010}},
    "intensity -5 mm/decade": {"systematic": {"intensity_bias_m_per_decade": -0.005,
                                              "intensity_ref_counts": 1000.0}},
    "incidence 10 mm/rad": {"systematic": {"incidence_bias_m": 0.010}},
    "drift 10 mm, tau 600 s": {"systematic": {"drift_amplitude_m": 0.010, "drift_time_constant_s": 600.0}},
    "all four": {"systematic": {"range_offset_m": 0.010, "intensity_bias_m_per_decade": -0.005,
                                "incidence_bias_m": 0.010, "drift_amplitude_m": 0.010,
                                "drift_time_constant_s": 600.0}},
    "echoes, read /echoes strongest": {"echoes": {"enabled": True}},
}


def _scenario(base: str, case: str, sensor: dict[str, object]):  # type: ignore[no-untyped-def]
    data = copy.deepcopy(yaml.safe_load((ROOT / "scenarios" / f"{base}.yaml").read_text()))
    data["name"] = f"{base}_" + "".join(c if c.isalnum() else "_" for c in case)
    data.setdefault("sensor", {}).update(copy.deepcopy(sensor))
    return parse_scenario(data, f"{base} + {case}")


def _use_echoes(folder: Path, topic: str) -> None:
    """Point the recording's rig file at the MultiEchoLaserScan topic (strongest echo)."""
    path = folder / "nominal.yaml"
    rig = yaml.safe_load(path.read_text())
    rig["scan"] = {"topic": topic, "stamp": "header", "echo": "strongest"}
    path.write_text(yaml.safe_dump(rig, sort_keys=False))


def run_case(base: str, case: str, sensor: dict[str, object], tmp: Path) -> Trial:
    sc = _scenario(base, case, sensor)
    folder = record(sc, tmp / sc.name)
    if sc.sensor.echoes.enabled:
        _use_echoes(folder, sc.sensor.echoes.topic)
    return calibrate_recording(folder, name=case)


def _row(base: str, t: Trial) -> str:
    if t.status != "calibrated":
        return f"{base:12s} {t.name:32s} refused (exit {t.exit_code}): {t.reason[:80]}"
    cells = []
    for name, e, s in zip(DH_NAMES, t.errors, t.sigma, strict=True):
        k = 1000.0 if name in ("a", "b") else math.degrees(1.0)
        cells.append(f"{e * k:+8.3f} {s * k:6.3f}")
    zmax = float(np.max(np.abs(t.z)))
    flag = "  CONFIDENT WRONG" if zmax > CONFIDENT_WRONG_Z else ""
    return f"{base:12s} {t.name:32s} " + "  ".join(cells) + f"  {zmax:6.1f}{flag}"


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenarios", nargs="+", default=["tunnel_v", "plane_30deg"])
    args = ap.parse_args(argv)
    print(f"{'scenario':12s} {'case':32s} " + "  ".join(
        f"{n + (' [mm]' if n in ('a', 'b') else ' [deg]'):>15s}" for n in DH_NAMES) + "  max|z|")
    print(f"{'':12s} {'':32s} " + "  ".join(f"{'error':>8s} {'sigma':>6s}" for _ in DH_NAMES))
    t0 = time.perf_counter()
    n_wrong = 0
    with tempfile.TemporaryDirectory() as tmp:
        for base in args.scenarios:
            for case, sensor in CASES.items():
                t = run_case(base, case, sensor, Path(tmp))
                n_wrong += t.confident_wrong
                print(_row(base, t), flush=True)
    print(f"\n{n_wrong} confident wrong result(s) (|error| > {CONFIDENT_WRONG_Z:g} sigma); the calibration does not "
          f"estimate these effects yet. {time.perf_counter() - t0:.0f} s")
    return 0


if __name__ == "__main__":
    sys.exit(main())
