"""Before/after: calibration.yaml of every shipped scenario from two versions of the code, compared number by number.

    python benchmarks/before_after.py --base /tmp/base/src --new src --work /tmp/before_after

simulates each scenario once (``lrfsim simulate``, with the new code; skipped where ``WORK/<name>`` exists), runs
``lrfcal calibrate --no-figures`` on it with each ``src`` first on PYTHONPATH (``--targetless`` for the targetless
scenarios), and compares every number of the two calibration.yaml files: the largest relative difference per
scenario, and each number that differs by more than ``--rtol`` (default 1e-9), with its difference in sigma where
the number is an estimate with a sigma beside it (every leaf but the stages' wall-clock ``timings_s``). Exit code 1
when a scenario's exit codes or strings differ or a number differs beyond ``--rtol``.
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
from pathlib import Path

import yaml

SCENARIOS = ("plane_0deg", "plane_30deg", "tunnel_v", "tunnel_v_systematic", "spinning_tilted", "cardboard_box",
             "room_box")
TARGETLESS = ("cardboard_box", "room_box")
ROOT = Path(__file__).resolve().parents[1]


def _run(src: Path, args: list[str], log: Path) -> int:
    env = {**os.environ, "PYTHONPATH": str(src)}
    with log.open("w") as out:
        return subprocess.run(args, env=env, stdout=out, stderr=subprocess.STDOUT, check=False).returncode


def _leaves(node: object, path: str = "") -> dict[str, object]:
    """Every leaf of a YAML tree by its dotted path."""
    if isinstance(node, dict):
        return {k: v for key, val in node.items()
                for k, v in _leaves(val, f"{path}.{key}" if path else str(key)).items()}
    if isinstance(node, list):
        return {k: v for i, val in enumerate(node) for k, v in _leaves(val, f"{path}[{i}]").items()}
    return {path: node}


def compare(base: dict, new: dict, rtol: float) -> tuple[float, list[str]]:
    """The largest relative difference of the numbers of two calibration.yaml trees, and one line per leaf that
    differs (numbers beyond ``rtol``; strings, missing leaves)."""
    a, b = _leaves(base), _leaves(new)
    worst, lines = 0.0, []
    for key in sorted(set(a) | set(b)):
        if key.startswith("timings_s"):  # wall-clock times: not results
            continue
        x, y = a.get(key, "<missing>"), b.get(key, "<missing>")
        if isinstance(x, (int, float)) and isinstance(y, (int, float)) and not isinstance(x, bool):
            if x == y:
                continue
            rel = abs(x - y) / max(abs(x), abs(y), 1e-300)
            worst = max(worst, rel)
            if rel > rtol:
                sig = a.get(key.rsplit(".", 1)[0] + ".sigma") if key.endswith(".value") else None
                in_sigma = f" = {abs(x - y) / sig:.2e} sigma" if isinstance(sig, float) and sig > 0 else ""
                lines.append(f"  {key}: {x!r} -> {y!r} (relative {rel:.2e}{in_sigma})")
        elif x != y:
            lines.append(f"  {key}: {x!r} -> {y!r}")
    return worst, lines


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--base", type=Path, required=True, help="the base version's src folder")
    p.add_argument("--new", type=Path, default=ROOT / "src", help="the new version's src folder")
    p.add_argument("--work", type=Path, default=Path("/tmp/before_after"))
    p.add_argument("--rtol", type=float, default=1e-9)
    p.add_argument("--only", nargs="*", default=list(SCENARIOS))
    p.add_argument("--reuse-base", action="store_true", help="keep WORK/base_<name> where it exists")
    a = p.parse_args()
    a.work.mkdir(parents=True, exist_ok=True)
    bad = 0
    for name in a.only:
        rec = a.work / name
        if not rec.exists():
            _run(a.new.resolve(), ["lrfsim", "simulate", str(ROOT / "scenarios" / f"{name}.yaml"), "-o", str(rec)],
                 a.work / f"sim_{name}.log")
        extra = ["--targetless"] if name in TARGETLESS else []
        codes = {}
        for tag, src in (("base", a.base), ("new", a.new)):
            out = a.work / f"{tag}_{name}"
            if tag == "base" and a.reuse_base and (out / "calibration.yaml").exists():
                codes[tag] = 0
                continue
            codes[tag] = _run(src.resolve(), ["lrfcal", "calibrate", str(rec), "-o", str(out), "--no-figures",
                                              "--overwrite", *extra], a.work / f"{tag}_{name}.log")
        if codes["base"] != codes["new"]:
            print(f"{name}: exit codes differ: {codes}")
            bad += 1
            continue
        files = [a.work / f"{tag}_{name}" / "calibration.yaml" for tag in ("base", "new")]
        if not all(f.exists() for f in files):
            print(f"{name}: exit code {codes['new']} both, no calibration.yaml")
            continue
        worst, lines = compare(*(yaml.safe_load(f.read_text()) for f in files), a.rtol)
        print(f"{name}: largest relative difference {worst:.2e}, {len(lines)} beyond {a.rtol:g}")
        print("\n".join(lines[:40]))
        bad += bool(lines)
    return 1 if bad else 0


if __name__ == "__main__":
    sys.exit(main())
