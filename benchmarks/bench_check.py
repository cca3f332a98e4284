"""`lrfcal check`'s targets (issue 55, docs/check.md): the false-alarm rate without drift, the detection rate of a
drift, and a check's cost against a calibration of the same recording.

    python benchmarks/bench_check.py [--pairs 100] [--detect-pairs 50] [-j 2] [-o runs/bench_check] [--only NAME]

Runs `lrfsim study SCENARIO --drift ...` (lrfsim.trials.drift) for each study below through the installed console
script, then `lrfcal calibrate` and `lrfcal check` on one tunnel_v pair, interleaved, for their cost; writes each
study's folder and results.md into the output folder and prints the tables.

- false alarms (``--pairs`` pairs, no drift): tunnel_v (with the mount moved by 10 cm and 5 deg, DH unchanged, in
  the same pairs), plane_30deg, tunnel_v with range noise correlated 0.7 along the scan, room_box (targetless);
- detection (``--detect-pairs`` pairs, tunnel_v): each DH parameter alone at the drift `lrfsim plan` says the check
  detects with 95 % probability, and a 2 mm, b 1 mm, alpha 0.05 deg, beta 0.1 deg, clock offset 2 ms.
"""

from __future__ import annotations

import argparse
import json
import math
import resource
import subprocess
import sys
import time
from pathlib import Path

import yaml

ROOT = Path(__file__).resolve().parents[1]
SCEN = ROOT / "scenarios"
FIXED_DRIFTS = ["a=2mm", "b=1mm", "alpha=0.05deg", "beta=0.1deg", "clock_offset=2ms"]


def _script(name: str) -> str:
    here = Path(sys.executable).parent / name
    return str(here) if here.is_file() else name


def _scenario(out: Path, name: str, base: str, changes: dict[str, object]) -> Path:
    """scenarios/<base>.yaml with ``changes`` (dotted keys), written as out/<name>.yaml."""
    data = yaml.safe_load((SCEN / f"{base}.yaml").read_text())
    data["name"] = name
    for dotted, value in changes.items():
        node = data
        *head, last = dotted.split(".")
        for k in head:
            node = node.setdefault(k, {})
        node[last] = value
    path = out / f"{name}.yaml"
    path.write_text(yaml.safe_dump(data, sort_keys=False))
    return path


def plan_drifts(scenario: Path) -> list[str]:
    """The drift of each DH parameter alone `lrfsim plan` says the check detects with 95 % probability."""
    proc = subprocess.run([_script("lrfsim"), "plan", str(scenario), "--json", "-q"], capture_output=True, text=True,
                          check=True)
    d = json.loads(proc.stdout)["check_detects_95"]
    return [f"a={d['a'] * 1000:.4g}mm", f"alpha={math.degrees(d['alpha']):.4g}deg", f"b={d['b'] * 1000:.4g}mm",
            f"beta={math.degrees(d['beta']):.4g}deg"]


def study(out: Path, name: str, scenario: Path, drifts: list[str], pairs: int, workers: int) -> str:
    """Run one drift study; return its summary's table."""
    folder = out / name
    args = [_script("lrfsim"), "study", str(scenario), "-n", str(pairs), "-j", str(workers), "-q", "-o", str(folder),
            "--overwrite", *(x for d in drifts for x in ("--drift", d))]
    t0 = time.perf_counter()
    proc = subprocess.run(args, capture_output=True, text=True)
    if proc.returncode != 0:
        raise SystemExit(f"{' '.join(args)}: exit {proc.returncode}: {proc.stderr}")
    text = (folder / "summary.md").read_text()
    print(f"## {name} ({time.perf_counter() - t0:.0f} s)\n\n{text}", flush=True)
    return f"## {name}\n\n`{' '.join(['lrfsim', *args[1:]])}`\n\n{text}"


def _children_cpu() -> float:
    r = resource.getrusage(resource.RUSAGE_CHILDREN)
    return r.ru_utime + r.ru_stime


def cost(out: Path, repeats: int) -> str:
    """`lrfcal calibrate REC` (as a user runs it, figures and all, and with --no-figures) against `lrfcal check CAL
    REC` (and --no-figures) on one tunnel_v pair, interleaved, ``repeats`` times each: wall and CPU seconds."""
    work = out / "cost"
    work.mkdir(parents=True, exist_ok=True)
    sc2 = _scenario(work, "tunnel_v_b", "tunnel_v", {"seed": 2})
    for src, rec in ((SCEN / "tunnel_v.yaml", work / "rec_a"), (sc2, work / "rec_b")):
        if not rec.exists():
            subprocess.run([_script("lrfsim"), "simulate", str(src), "-o", str(rec), "-q"], check=True,
                           capture_output=True)
    cal = work / "cal_a"
    subprocess.run([_script("lrfcal"), "calibrate", str(work / "rec_a"), "-o", str(cal), "-q", "--overwrite"],
                   check=True, capture_output=True)
    runs = {
        "calibrate": [_script("lrfcal"), "calibrate", str(work / "rec_b"), "-o", str(work / "cal_b"), "-q",
                      "--overwrite"],
        "calibrate --no-figures": [_script("lrfcal"), "calibrate", str(work / "rec_b"), "-o", str(work / "cal_b"),
                                   "-q", "--overwrite", "--no-figures"],
        "check": [_script("lrfcal"), "check", str(cal), str(work / "rec_b"), "-o", str(work / "chk"), "-q",
                  "--overwrite"],
        "check --no-figures": [_script("lrfcal"), "check", str(cal), str(work / "rec_b"), "-o", str(work / "chk"),
                               "-q", "--overwrite", "--no-figures"],
    }
    times: dict[str, list[tuple[float, float]]] = {k: [] for k in runs}
    for _ in range(repeats):
        for k, args in runs.items():
            c0, t0 = _children_cpu(), time.perf_counter()
            proc = subprocess.run(args, capture_output=True, text=True)
            if proc.returncode not in (0, 4):
                raise SystemExit(f"{k}: exit {proc.returncode}: {proc.stderr}")
            times[k].append((time.perf_counter() - t0, _children_cpu() - c0))
    med = {k: (sorted(w for w, _ in v)[len(v) // 2], sorted(c for _, c in v)[len(v) // 2]) for k, v in times.items()}
    lines = ["## Cost of a check against a calibration of the same recording (tunnel_v)", "",
             f"Median of {repeats} runs each, interleaved, through the console scripts (wall and CPU seconds).", "",
             "| command | wall [s] | CPU [s] | wall / calibrate's |", "|---|---|---|---|"]
    for k, (w, c) in med.items():
        base = med["calibrate --no-figures" if "no-figures" in k else "calibrate"][0]
        lines.append(f"| lrfcal {k} | {w:.2f} | {c:.2f} | {w / base:.2f} |")
    text = "\n".join(lines) + "\n"
    print(text, flush=True)
    return text


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--pairs", type=int, default=100)
    ap.add_argument("--detect-pairs", type=int, default=50)
    ap.add_argument("-j", "--workers", type=int, default=2)
    ap.add_argument("-o", "--out", type=Path, default=Path("runs/bench_check"))
    ap.add_argument("--only", action="append", default=[],
                    help="run only these parts: tunnel_v, plane_30deg, tunnel_v_rho07, room_box, detection, cost")
    ap.add_argument("--repeats", type=int, default=5)
    a = ap.parse_args()
    a.out.mkdir(parents=True, exist_ok=True)
    want = set(a.only) or {"tunnel_v", "plane_30deg", "tunnel_v_rho07", "room_box", "detection", "cost"}
    parts = []
    if "tunnel_v" in want:
        parts.append(study(a.out, "tunnel_v", SCEN / "tunnel_v.yaml", ["none", "x=10cm,yaw=5deg"], a.pairs,
                           a.workers))
    if "plane_30deg" in want:
        parts.append(study(a.out, "plane_30deg", SCEN / "plane_30deg.yaml", ["none"], a.pairs, a.workers))
    if "tunnel_v_rho07" in want:
        rho = _scenario(a.out, "tunnel_v_rho07", "tunnel_v", {"sensor.noise_correlation": 0.7})
        parts.append(study(a.out, "tunnel_v_rho07", rho, ["none"], a.pairs, a.workers))
    if "room_box" in want:
        parts.append(study(a.out, "room_box", SCEN / "room_box.yaml", ["none"], a.pairs, a.workers))
    if "detection" in want:
        drifts = plan_drifts(SCEN / "tunnel_v.yaml") + FIXED_DRIFTS
        parts.append(study(a.out, "tunnel_v_detection", SCEN / "tunnel_v.yaml", drifts, a.detect_pairs, a.workers))
    if "cost" in want:
        parts.append(cost(a.out, a.repeats))
    (a.out / "results.md").write_text("\n".join(parts))
    print(f"wrote {a.out / 'results.md'}")


if __name__ == "__main__":
    main()
