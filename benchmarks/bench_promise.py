"""One promise (issue 56): `lrfsim plan` and `lrfcal calibrate` judge "determined" by one rule, no mirror twin passes,
and no calibration is confidently wrong, on random rigs no one has run before.

For each seed of lrfsim.testing.random_scenarios.random_scenario_wide(seed, broad=True) (a third each: the scan plane
along the motor axis, tilted 20-70 deg, near perpendicular to it; V layouts, boards, points; sweeps and spins): the
scenario is simulated, planned (lrfsim.plan.prediction.plan, what `lrfsim plan --json` prints) and calibrated
(lrfsim.trials.trial.calibrate_recording, what `lrfcal calibrate` does). Printed per rig: plan's verdict ("determined"
or its reason) against calibrate's outcome (exit 0, or the refusal's check), and for a calibration the DH errors in
their sigma; then the summary:

  - plan agrees with calibrate (plan determined and exit 0, or plan not determined and exit 3): target >= 95 %;
  - plan says determined where its own table shows a DH sigma over its limit: target 0;
  - confident wrong (exit 0 and some DH error beyond 4 sigma, as bench_trust counts it): target 0;
  - refused naming the mirror image, per attitude kind.

``--rho R`` gives every rig range noise correlated along the scan (sensor.noise_correlation R; real URG-04LX
recordings show 0.56-0.7): the selections that judge a return by its neighbours (the marker surfaces' scan-line rule)
keep the returns whose noise reads one way where they misjudge, which independent noise does not show.

    python benchmarks/bench_promise.py [--first 1000] [--seeds 100] [--rho 0.7]
"""

from __future__ import annotations

import argparse
import shutil
import tempfile
from collections import Counter
from pathlib import Path

from lrfcal.estimate.observability import LIMITS
from lrfcal.model.kinematics import DH_NAMES
from lrfsim.plan.prediction import plan
from lrfsim.testing.random_scenarios import alpha_kind_of, random_scenario_wide
from lrfsim.trials.trial import calibrate_recording, record
from lrfsim.trials.variants import with_field


def _head(reason: str) -> str:
    return reason.split(":")[0] if reason else ""


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--first", type=int, default=1000, help="the first seed (new rigs: beyond bench_trust's 0-149)")
    ap.add_argument("--seeds", type=int, default=100)
    ap.add_argument("--rho", type=float, default=None, help="range noise correlated along the scan (0-0.99)")
    args = ap.parse_args()
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for seed in range(args.first, args.first + args.seeds):
            sc = random_scenario_wide(seed, broad=True)
            if args.rho is not None:
                sc = with_field(sc, "sensor.noise_correlation", args.rho)
            kind = alpha_kind_of(sc)
            folder = record(sc, Path(tmp) / sc.name)
            try:
                p = plan(sc)
                determined, why = p.determined, p.verdict.reason()
                over = [n for n in DH_NAMES if not p.sigma[n] <= LIMITS[n]]
            except Exception as err:  # noqa: BLE001 - a plan that cannot run is a row, not the end of the benchmark
                determined, why, over = False, f"plan failed: {err}", []
            trial = calibrate_recording(folder)
            shutil.rmtree(folder)
            calibrated = trial.status == "calibrated"
            rows.append((seed, kind, determined, calibrated, trial, over))
            outcome = ("exit 0, z " + ", ".join(f"{n} {z:+.1f}" for n, z in zip(DH_NAMES, trial.z, strict=True))
                       if calibrated else f"exit 3: {trial.reason[:150]}")
            verdict = "determined" if determined else f"NOT determined: {why[:150]}"
            flag = ("" if determined == calibrated else "DISAGREE ") + ("CONFIDENT WRONG " if trial.confident_wrong
                                                                        else "")
            print(f"seed {seed} {kind}: {flag}plan {verdict} | calibrate {outcome}"
                  + (f" | plan's table over the limit: {', '.join(over)}" if over and determined else ""), flush=True)
    n = len(rows)
    agree = sum(d == c for _, _, d, c, _, _ in rows)
    contradict = sum(d and bool(over) for _, _, d, _, _, over in rows)
    wrong = sum(t.confident_wrong for *_, t, _ in rows)
    print(f"\nrigs {n}: plan agrees with calibrate on {agree} ({100.0 * agree / max(n, 1):.0f} %; target >= 95 %)")
    print(f"plan says determined with a DH sigma over its limit in its own table: {contradict} (target 0)")
    print(f"confident wrong: {wrong} (target 0)")
    for kind in sorted({k for _, k, *_ in rows}):
        sub = [r for r in rows if r[1] == kind]
        refused = Counter(_head(t.reason) for *_, t, _ in sub if t.status != "calibrated")
        print(f"  {kind}: {len(sub)} rigs, {sum(r[3] for r in sub)} calibrated, plan agrees on "
              f"{sum(r[2] == r[3] for r in sub)}, refused by " + ", ".join(f"{k} {v}" for k, v in refused.items()))
    print(f"(seeds {args.first}-{args.first + args.seeds - 1}"
          + (f", range noise correlated along the scan, rho {args.rho:g})" if args.rho is not None else ")"))


if __name__ == "__main__":
    main()
