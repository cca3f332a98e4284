"""The real URG-04LX recordings calibrated targetless from every scan, the even scans and the odd scans (issue 54).

For each shared bag (../shared/realbags/cardboard_box.bag and room_240.bag, github liangfok/tilting_lidar_scanner @
438ea81; skipped when absent) the targetless calibration from the stand's design values (a = 0, alpha = 90 deg,
b = 0.08 m, beta = 0: the authors' model) is run three times: on every scan, on the even scans only and on the odd
scans only (each half written as a ROS 1 bag of every other message, as a user would cut it). Printed per run: the
verdict `lrfcal calibrate` gives (exit 0, or exit 3 and the check it names), the estimate with --force (value +- 1
sigma of every DH parameter, held ones marked) and the held-out planes (every 5th scan left out of the fit: their
thickness with the design values and with the calibrated DH). Then per bag: whether the three verdicts are one and
the largest difference between two runs' estimates in their combined sigma. Targets: one exit code per bag, and
where exit 0 the runs within 2 combined sigma and the held-out planes no thicker than with the design values.

    python benchmarks/bench_real_halves.py [--range-pattern]

``--range-pattern``: the rig file declares the scanner's range error along the scan (``range_pattern: true``: the
calibration estimates it with the DH, lrfcal.model.range_pattern).
"""

from __future__ import annotations

import argparse
import math
import tempfile
from pathlib import Path

from lrfcal.config import CalibConfig
from lrfcal.errors import CalibrationError
from lrfcal.estimate.checks import refuse_failed
from lrfcal.io.recording import read_recording
from lrfcal.pipeline import calibrate
from lrfcal.result import CalibrationResult

REALBAGS = Path(__file__).resolve().parents[2] / "shared" / "realbags"
DH = ("a", "alpha", "b", "beta")
RIG = """dh: {a: 0.0, alpha: 1.5707963267948966, b: 0.08, beta: 0.0}
scan: {topic: /slice, field: laserScan, stamp: header}
servo: {field: stepAngle, unit: deg, sign: 1, offset_rad: 0.0, stamp: scan, motion: step}
"""


def half_bag(src: Path, half: str, out: Path) -> Path:
    """A ROS 1 bag of every other message of each topic (``half``: "even" or "odd") of ``src``."""
    from rosbags.rosbag1 import Reader, Writer

    with Reader(src) as r, Writer(out) as w:
        conns = {c.id: w.add_connection(c.topic, c.msgtype, msgdef=c.msgdef.data, md5sum=c.digest,
                                        callerid=c.ext.callerid, latching=c.ext.latching) for c in r.connections}
        count: dict[str, int] = {}
        for c, t, raw in r.messages():
            k = count.get(c.topic, 0)
            count[c.topic] = k + 1
            if (k % 2 == 0) == (half == "even"):
                w.write(conns[c.id], t, raw)
    return out


def verdict(result: CalibrationResult) -> str:
    try:
        refuse_failed(list(result.checks), CalibConfig(targetless=True))
        return "exit 0"
    except CalibrationError as err:
        return "exit 3: " + str(err).split(";")[0][:160]


def text(result: CalibrationResult) -> str:
    s, dh, held = result.solution, result.solution.params.dh, result.evidence.plane_fit.held  # type: ignore[union-attr]
    parts = []
    for i, n in enumerate(DH):
        v, sg = getattr(dh, n), s.sigma[6 + i]
        if n in ("alpha", "beta"):
            parts.append(f"{n} {math.degrees(v):.2f}" + (" (held)" if n in held else f" +- {math.degrees(sg):.2f} deg"))
        else:
            parts.append(f"{n} {v * 1000:.1f}" + (" (held)" if n in held else f" +- {sg * 1000:.1f} mm"))
    held_out = next(c for c in result.checks if c.name == "held-out planes").detail.split(": the")[0]
    return ", ".join(parts) + f"; held-out planes: {held_out}"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--range-pattern", action="store_true", help="the rig file declares range_pattern: true")
    args = ap.parse_args()
    if not REALBAGS.is_dir():
        print(f"skipped: {REALBAGS} is absent (the shared real recordings, not part of a clone)")
        return
    with tempfile.TemporaryDirectory() as tmp:
        rig = Path(tmp) / "rig.yaml"
        rig.write_text(RIG + ("range_pattern: true\n" if args.range_pattern else ""))
        for name in ("cardboard_box", "room_240"):
            src = REALBAGS / f"{name}.bag"
            runs = []
            for half in ("all", "even", "odd"):
                bag = src if half == "all" else half_bag(src, half, Path(tmp) / f"{name}_{half}.bag")
                rec = read_recording(None, bag=bag, nominal=rig, require_distances=False, warn=lambda _t: None)
                result = calibrate(rec, CalibConfig(targetless=True, force=True, clouds=False, geometry=False))
                runs.append(result)
                print(f"{name} {half}: {verdict(result)}\n    {text(result)}", flush=True)
            one = len({":".join(verdict(r).split(":")[:2]) for r in runs}) == 1  # exit code and the check named
            worst = 0.0
            for i in range(3):
                for j in range(i + 1, 3):
                    a, b = runs[i].solution, runs[j].solution
                    for k, n in enumerate(DH):
                        sa, sb = a.sigma[6 + k], b.sigma[6 + k]
                        if math.isfinite(sa) and math.isfinite(sb):
                            d = getattr(a.params.dh, n) - getattr(b.params.dh, n)
                            d = math.remainder(d, 2 * math.pi) if n in ("alpha", "beta") else d
                            worst = max(worst, abs(d) / math.hypot(sa, sb))
            print(f"{name}: one verdict for all three: {'yes' if one else 'NO'}; largest difference between two runs "
                  f"{worst:.1f} combined sigma\n", flush=True)


if __name__ == "__main__":
    main()
