"""Trust benchmark (issue 7): never a confident wrong calibration.

Runs the calibration on
  1. broad random ground truths (lrfsim.testing.random_scenarios.random_scenario_wide: V on one or both walls,
     markers on walls, floor and ceiling, a board; DH angles near 0 or +-90 deg with either sign; the motor axis
     along, across and up the tunnel; 6-30 markers; 1-4 passes), and
  2. a fault set on tunnel_v and plane_30deg (false blobs, occluded markers, dropped scans, encoder spikes,
     undeclared clock offsets, tape outliers, an inverted servo, 3x range noise, a gear ratio 2 % off, joint states
     at 2 Hz, ranges 1 % long, joint states missing for 3 s across the servo's first turnaround),
and prints per case the outcome (calibrated with error / sigma, or refused with the reason), then
  - the number of confident wrong results (exit 0 and some DH error beyond 4 sigma): must be 0;
  - the refusal rate, over all random truths and over those whose layout the generator labels as determining
    the DH parameters (lrfsim.testing.random_scenarios.wide_dh_determined; target below 10 %);
  - the RMS of error / sigma per DH parameter over the calibrated cases (target 0.8-1.25);
  - the calibration time against the code before the trust work (``--baseline-rev``, run from a git worktree
    in the same run on the same recordings; target at most 2x).

With ``--broad`` the random truths also tilt the scan plane (random_scenario_wide(seed, broad=True): by seed in
turn, alpha along the motor axis (+-90 +- 3 deg), tilted (|alpha| 20-70 deg, a sweep or a spin) and near
perpendicular to it (|alpha| 0-15 deg, a spin), a third each), and the summary adds per attitude kind: calibrated,
refused (by the first words of the reason; near perpendicular, b is the mount's own offset along the motor axis
and is refused when not determined), confident wrong (must be 0) and the RMS of error / sigma per DH parameter.

    python benchmarks/bench_trust.py [--seeds 50] [--broad] [--baseline-rev 399a633] [--skip-faults] [--skip-timing]
"""

from __future__ import annotations

import argparse
import math
import re
import shutil
import subprocess
import sys
import tempfile
import time
from collections import Counter
from dataclasses import replace
from pathlib import Path

import numpy as np
import yaml

from lrfcal.model.kinematics import DH_NAMES
from lrfsim.scenario.file import Scenario, parse_scenario, with_changes
from lrfsim.testing.random_scenarios import ALPHA_KINDS, alpha_kind_of, random_scenario_wide, wide_dh_determined
from lrfsim.trials.trial import Trial, calibrate_recording, record

ROOT = Path(__file__).resolve().parents[1]

FAULTS: dict[str, dict[str, object]] = {
    "false blobs (5)": {"faults.false_blobs": 5},
    "occluded markers (3)": {"faults.occluded_markers": 3},
    "dropped scans (5 %)": {"faults.dropped_scans_fraction": 0.05},
    "encoder spikes (20)": {"faults.encoder_spikes": 20},
    "clock offset 20 ms (undeclared)": {"servo.clock_offset_s": 0.02},
    "clock offset 100 ms (undeclared)": {"servo.clock_offset_s": 0.1},
    "tape outlier 5 cm": {"faults.tape_outliers": [{"pair": 3, "error_m": 0.05}]},
    "tape outlier 0.5 m": {"faults.tape_outliers": [{"pair": 3, "error_m": 0.5}]},
    "tape outlier 1 m": {"faults.tape_outliers": [{"pair": 3, "error_m": 1.0}]},
    "inverted servo": {"faults.inverted_servo": True},
    "3x range noise": {"faults.range_noise_scale": 3.0},
    "gear ratio 2 %": {"faults.gear_ratio": 1.02},
    "joint states at 2 Hz": {"faults.joint_rate_hz": 2.0},
    "range scale 1 %": {"faults.range_scale": 1.01},
    "joint states missing 3 s across a turnaround": {"faults.joint_gap_s": 3.0},
    # one scan line per marker: the markers alone do not determine the DH (lrfcal.stages.refinement)
    "fast single sweep (90 deg/s, one pass)": {"servo.speed_rad_s": math.radians(90.0), "servo.passes": 1},
}


def _scenario(base: str, name: str, changes: dict[str, object]) -> Scenario:
    data = yaml.safe_load((ROOT / "scenarios" / f"{base}.yaml").read_text())
    return parse_scenario(with_changes(data, {"name": name, **changes}), name)


def _line(trial: Trial, tag: str = "") -> str:
    flag = "CONFIDENT WRONG " if trial.confident_wrong else ""
    scales = f" [estimated: {', '.join(_scales_estimated(trial))}]" if _scales_estimated(trial) else ""
    return f"  {flag}{tag}{trial.describe()}{scales} [{trial.seconds:.1f} s]"


def _scales_estimated(trial: Trial) -> tuple[str, ...]:
    """The intrinsics held by default that this calibration estimated (lrfcal.stages.markers' score tests)."""
    if trial.result is None:
        return ()
    return tuple(n for n, (_, s) in trial.result.solution.intrinsics.items()
                 if n.endswith("_scale") and math.isfinite(s))


def _calibrate(folder: Path, **kw: object) -> Trial:
    """calibrate_recording, keeping of the result only what the summary reads (the clouds are large)."""
    trial = calibrate_recording(folder, keep_result=True, **kw)  # type: ignore[arg-type]
    if trial.result is not None:
        trial = replace(trial, result=replace(trial.result, cloud_before_M=np.zeros((0, 3)),
                                              cloud_after_M=np.zeros((0, 3)), cloud_intensity=np.zeros(0)))
    return trial


def run_cases(seeds: int, faults: bool, work: Path, broad: bool = False
              ) -> tuple[list[tuple[Trial, bool, str]], list[Trial]]:
    """The random truths as (trial, labelled as determining the DH, attitude kind), and the fault set."""
    random_trials: list[tuple[Trial, bool, str]] = []
    print(f"random truths (random_scenario_wide{', broad' if broad else ''}, seeds 0-{seeds - 1}):")
    for seed in range(seeds):
        sc = random_scenario_wide(seed, broad=broad)
        determined = wide_dh_determined(sc)
        folder = record(sc, work / sc.name)
        trial = _calibrate(folder)
        random_trials.append((trial, determined, alpha_kind_of(sc)))
        print(_line(trial, "" if determined else "(label: weak layout) "), flush=True)
        shutil.rmtree(folder)
    fault_trials: list[Trial] = []
    if faults:
        print("fault set:")
        for base in ("tunnel_v", "plane_30deg"):
            for label, changes in FAULTS.items():
                name = f"{base}: {label}"
                sc = _scenario(base, f"{base}_{len(fault_trials)}", changes)
                folder = record(sc, work / sc.name)
                trial = _calibrate(folder, name=name)
                fault_trials.append(trial)
                print(_line(trial), flush=True)
                shutil.rmtree(folder)
    return random_trials, fault_trials


_TIMING = """
import sys, time
from lrfcal.io.recording import read_recording
from lrfcal.pipeline import calibrate, CalibConfig
rec = read_recording(sys.argv[1])
best = float("inf")
for _ in range(int(sys.argv[2])):
    t = time.perf_counter(); calibrate(rec, CalibConfig()); best = min(best, time.perf_counter() - t)
print(best)
"""


def _reason_head(reason: str, words: int = 8) -> str:
    """The first words of a refusal: the failed check's name, or its sentence up to the first colon or bracket."""
    return " ".join(re.split(r"[:(]", reason)[0].split()[:words]).rstrip(",")


def by_kind(random_trials: list[tuple[Trial, bool, str]]) -> list[str]:
    """Summary lines per attitude kind (ALPHA_KINDS): calibrated, refused by reason, confident wrong, RMS of
    error / sigma per DH parameter over the calibrated ones."""
    lines = []
    for kind in ALPHA_KINDS:
        trials = [(t, d) for t, d, k in random_trials if k == kind]
        if not trials:
            continue
        cal = [t for t, _ in trials if t.status == "calibrated"]
        refused = Counter(_reason_head(t.reason) for t, _ in trials if t.status == "refused")
        labelled = sum(d for _, d in trials)
        lines.append(f"  {kind} ({len(trials)} truths, {labelled} labelled as determining the DH): "
                     f"{len(cal)} calibrated, {sum(refused.values())} refused, "
                     f"{sum(t.confident_wrong for t in cal)} confident wrong")
        lines += [f"    refused {n}x: {head}" for head, n in refused.most_common()]
        if cal:
            rms = np.sqrt(np.mean(np.array([t.z for t in cal]) ** 2, axis=0))
            lines.append("    RMS of error / sigma: " + ", ".join(f"{n} {v:.2f}" for n, v in zip(DH_NAMES, rms,
                                                                                                 strict=True)))
    return lines


def timing(rev: str, work: Path, repeats: int = 3) -> list[tuple[str, float, float]]:
    """(scenario, seconds now, seconds at ``rev``): the best of ``repeats`` full calibrations each, same recording."""
    tree = work / "baseline"
    subprocess.run(["git", "-C", str(ROOT), "worktree", "add", "--detach", "-f", str(tree), rev], check=True,
                   capture_output=True)
    rows = []
    try:
        for base in ("tunnel_v", "plane_30deg"):
            folder = record(_scenario(base, base, {}), work / f"timing_{base}")
            legacy = work / f"legacy_{base}"  # the old reader knows only the old rig-file keys
            shutil.copytree(folder, legacy)
            rig = yaml.safe_load((legacy / "nominal.yaml").read_text())
            old = {"dh": rig["dh"], "mount": rig["mount"], "marker_radius_m": rig["marker_radius_m"],
                   "scan_topic": rig["scan"]["topic"], "joint_topic": rig["servo"]["topic"],
                   "joint_name": rig["servo"]["joint"]}
            (legacy / "nominal.yaml").write_text(yaml.safe_dump(old))
            cmd = [sys.executable, "-c", _TIMING]
            now = float(subprocess.run([*cmd, str(folder), str(repeats)], check=True, capture_output=True, text=True,
                                       env={"PYTHONPATH": str(ROOT / "src"), "PATH": ""}).stdout.split()[-1])
            before = float(subprocess.run([*cmd, str(legacy), str(repeats)], check=True, capture_output=True,
                                          text=True, env={"PYTHONPATH": str(tree / "src"), "PATH": ""}
                                          ).stdout.split()[-1])
            rows.append((base, now, before))
    finally:
        subprocess.run(["git", "-C", str(ROOT), "worktree", "remove", "--force", str(tree)], capture_output=True)
    return rows


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--seeds", type=int, default=50)
    ap.add_argument("--baseline-rev", default="399a633", help="the code before the trust work")
    ap.add_argument("--broad", action="store_true", help="random truths with tilted and near-perpendicular scan "
                    "planes too (a third each), summarised per attitude kind")
    ap.add_argument("--skip-faults", action="store_true")
    ap.add_argument("--skip-timing", action="store_true")
    args = ap.parse_args()
    t0 = time.perf_counter()
    with tempfile.TemporaryDirectory(prefix="bench_trust-") as tmp:
        work = Path(tmp)
        random_trials, fault_trials = run_cases(args.seeds, not args.skip_faults, work, args.broad)
        rows = [] if args.skip_timing else timing(args.baseline_rev, work)

    every = [t for t, _, _ in random_trials] + fault_trials
    wrong = [t for t in every if t.confident_wrong]
    refused = [t for t, _, _ in random_trials if t.status == "refused"]
    det = [t for t, d, _ in random_trials if d]
    det_refused = [t for t in det if t.status == "refused"]
    calibrated = [t for t in every if t.status == "calibrated"]
    z = np.array([t.z for t in calibrated]) if calibrated else np.zeros((0, 4))
    print("\nsummary")
    print(f"  confident wrong results (exit 0, some |error| > 4 sigma): {len(wrong)} of {len(every)} runs")
    print(f"  random truths refused: {len(refused)} of {len(random_trials)} "
          f"({100 * len(refused) / max(len(random_trials), 1):.0f} %); on layouts labelled as determining the DH: "
          f"{len(det_refused)} of {len(det)} ({100 * len(det_refused) / max(len(det), 1):.0f} %, target < 10 %)")
    if fault_trials:
        print(f"  fault set: {sum(t.status == 'calibrated' for t in fault_trials)} calibrated within 4 sigma, "
              f"{sum(t.status == 'refused' for t in fault_trials)} refused, of {len(fault_trials)}")
    if len(z):
        rms = np.sqrt(np.mean(z**2, axis=0))
        print("  RMS of error / sigma over the calibrated runs (target 0.8-1.25): "
              + ", ".join(f"{n} {v:.2f}" for n, v in zip(DH_NAMES, rms, strict=True)) + f" (n = {len(z)})")
    if args.broad:
        named = Counter(n for t, _, _ in random_trials for n in _scales_estimated(t))
        print(f"  scales estimated on the random truths (their score test > 4 sigma; all false alarms, the truths "
              f"have none): {dict(named) or 'none'} of {len(random_trials)}")
        print("  per scan-plane attitude (alpha_kind_of the truth):")
        print("\n".join(by_kind(random_trials)))
    for base, now, before in rows:
        print(f"  calibration time {base}: {now:.2f} s now, {before:.2f} s at {args.baseline_rev} "
              f"(ratio {now / before:.2f}, target <= 2)")
    print(f"  benchmark wall time {time.perf_counter() - t0:.0f} s")
    if not math.isfinite(len(wrong)) or wrong:
        sys.exit(1)


if __name__ == "__main__":
    main()
