"""Is the stated sigma honest on every layout (issue 56, item 3)? RMS of error / reported sigma per DH parameter, and
plan's predicted sigma against the Monte-Carlo spread, on the shipped marker scenarios and on new random layouts of
each kind (a V, a board, scattered points), with uncorrelated range noise and with noise correlated along the scan
(rho 0.7, as measured on real URG-04LX recordings). The board is one the motor axis points at, turned 40-65 deg from
across it (random_scenario_wide(seed, layout="board_on_axis")): the generator's default board, beside the rig, leaves
b undetermined (its markers all at one distance from the motor axis: lrfsim.testing.boards) and was refused in every
trial, so it measured nothing.

Every trial is cast anew (`lrfsim study --recast`): the laser's phase on the markers (which beam cuts which part of a
marker) differs from one recording to the next, and the reported sigma holds that scatter (the calibration's
per-marker sandwich). A study on one cast (`lrfsim study` without --recast) freezes the phase: its error is then a
bias the same in every trial, the spread is narrower than a new recording's, and the sigma looks 1.2-1.4x too wide
(tunnel_v14: b 0.79, alpha 0.83 on one cast; 1.06 and 1.09 cast anew). Targets: RMS of error / sigma within
0.8-1.25 on each DH parameter of each case; plan's sigma within 25 % of the spread (RMSE / predicted within
0.75-1.25).

The band is narrower than the RMS's own sampling spread: from 24 trials of an exact sigma, RMS error / sigma is
sqrt(chi2_24 / 24), 0.72-1.28 in 95 % of draws, below 0.8 in 9.0 % and above 1.25 in 3.9 %, so about 13 % of the
parameters and (with four parameters a case) 12-22 of 40 cases fall outside it by chance alone. Each row therefore
also gives, per parameter, how likely an RMS that far from 1 is with an exact sigma (the two-sided chi-square
p-value of the n calibrated trials: lrfsim.trials.study_result.p_exact), and the summary: the count outside the
band that exact sigmas would give on the same trial counts (a Monte Carlo of normal errors,
:func:`chance_outside`), the parameters whose p-value is below 1 % and the RMS over all cases per parameter. Of
156 parameters, 7.8 fall below 5 % and 1.6 below 1 % by chance, so each below 5 % is then measured again on fresh
trials of its case (``--confirm``, 96 by default: RMS 0.86-1.14 in 95 % of draws of an exact sigma) and judged on
those alone at 1 %: a sigma that is wrong shows it again, an extreme draw does not (:func:`replicate`).

Where a case refuses some trials, the RMS is over the calibrated ones, and a refusal that the data decide can select
them: on points 2014 (b's sigma near its limit) the trials refused had the larger errors, and the RMS over the 9
calibrated of 24 was 0.40 where all 24, calibrated with --force, gave 0.64 (docs/study.md). So where the fresh
trials refuse some, the replication runs them with --force as well and gives the RMS over all of them.

    python benchmarks/bench_honesty.py [--trials 24] [--layouts 5] [--workers 2] [--only NAME] [--confirm 96]
"""

from __future__ import annotations

import argparse
import math
from pathlib import Path

import numpy as np
import yaml

from lrfcal.model.kinematics import DH_NAMES
from lrfsim.scenario.file import Scenario, parse_scenario
from lrfsim.testing.random_scenarios import random_scenario_wide
from lrfsim.trials.study import study
from lrfsim.trials.study_result import p_exact

ROOT = Path(__file__).resolve().parents[1]
SHIPPED = ("tunnel_v", "plane_0deg", "plane_30deg", "spinning_tilted", "tunnel_v_systematic")
#: the random layouts by kind (random_scenario_wide's layout names); the board is "board_on_axis", a board the motor
#: axis points at, turned obliquely: the generator's own "board" (beside the rig, facing the axis) has every marker at
#: about one distance from the motor axis, where b and the mount's turn about the axis are one direction, and both
#: `lrfsim plan` and `lrfcal calibrate` refused it in every trial (b's 1-sigma 14-55 mm; lrfsim.testing.boards)
KINDS = {"V": "v_both_walls", "board": "board_on_axis", "points": "scattered"}
RHOS = (0.0, 0.7)


def cases(n_layouts: int) -> list[tuple[str, Scenario]]:
    """(label, scenario): the shipped marker scenarios, then ``n_layouts`` new random layouts of each kind (seeds from
    2000 on, the scan plane along the motor axis as the shipped V and board are; the board's layout: KINDS)."""
    out = []
    for name in SHIPPED:
        data = yaml.safe_load((ROOT / "scenarios" / f"{name}.yaml").read_text())
        out.append((name, parse_scenario(data, name)))
    seed = 2000
    for kind, layout in KINDS.items():
        for _ in range(n_layouts):
            out.append((f"{kind} (seed {seed})", random_scenario_wide(seed, layout=layout)))
            seed += 1
    return out


#: the band RMS error / sigma is judged against, and the p-value below which an RMS is called the sigma's
BAND = (0.8, 1.25)
SIGNIFICANT = 0.01
#: the p-value below which a parameter is a suspect, measured again on fresh trials (and judged there at SIGNIFICANT)
SUSPECT = 0.05
#: the replication's seeds start this far past a case's own (its 24 trials use the case's seed on)
CONFIRM_SEED = 10_000


def chance_outside(counts: list[int], n_params: int = 4, draws: int = 4000, seed: int = 0) -> tuple[float, int, int]:
    """How many of the cases (their calibrated trial counts ``counts``) would have some parameter outside BAND if
    every sigma were exact and the parameters' errors independent: the mean and the 5-95 % range over ``draws``
    Monte-Carlo repetitions of normal errors."""
    rng = np.random.default_rng(seed)
    out = np.zeros(draws)
    for n in counts:
        rms = np.sqrt((rng.standard_normal((draws, n_params, n)) ** 2).mean(-1))
        out += ((rms < BAND[0]) | (rms > BAND[1])).any(-1)
    return float(out.mean()), int(np.percentile(out, 5)), int(np.percentile(out, 95))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--trials", type=int, default=24)
    ap.add_argument("--layouts", type=int, default=5)
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--only", default=None, help="run only the cases whose label starts with this")
    ap.add_argument("--confirm", type=int, default=96,
                    help="fresh trials for each parameter below p = 0.05 (0: no replication)")
    args = ap.parse_args()
    print("| case | rho | calibrated | RMS error / sigma (a, alpha, b, beta) "
          "| RMSE / plan's sigma (a, alpha, b, beta) | p_exact (a, alpha, b, beta) |")
    print("|---|---|---|---|---|---|")
    off_z, off_plan, n, refused = 0, 0, 0, 0
    counts: list[int] = []
    significant: list[str] = []
    flagged: dict[tuple[str, str], tuple[Scenario, list[str]]] = {}
    pooled: dict[str, list[tuple[float, int]]] = {name: [] for name in DH_NAMES}
    for label, sc in cases(args.layouts):
        if args.only and not label.startswith(args.only):
            continue
        s = study(sc, args.trials, workers=args.workers, recast=True,
                  vary=("sensor.noise_correlation", list(RHOS)))
        for part in s.parts:
            st = part.stats()
            z = [st[p]["rms_z"] for p in DH_NAMES]
            plan = [st[p]["rmse_over_predicted"] for p in DH_NAMES]
            cal = sum(r.status == "calibrated" for r in part.rows)
            if cal == 0:  # a layout both commands refuse: no sigma to judge (the refusal is the promise kept)
                refused += 1
                print(f"| {label} | {part.value} | 0/{len(part.rows)} | refused: {part.rows[0].reason[:90]} | - |",
                      flush=True)
                continue
            bad_z = [v for v in z if not BAND[0] <= v <= BAND[1]]
            bad_p = [v for v in plan if math.isfinite(v) and not 0.75 <= v <= 1.25]
            off_z, off_plan, n = off_z + bool(bad_z), off_plan + bool(bad_p), n + 1
            ns = [int(st[p]["n"]) for p in DH_NAMES]
            ps = [p_exact(v, k) for v, k in zip(z, ns, strict=True)]
            counts.append(min(ns))
            for name, v, k, pv in zip(DH_NAMES, z, ns, ps, strict=True):
                pooled[name].append((v, k))
                if pv < SIGNIFICANT:
                    significant.append(f"{label} rho {part.value} {name} {v:.2f} (p {pv:.4f})")
                if pv < SUSPECT:
                    flagged.setdefault((label, part.value), (sc, []))[1].append(name)
            print(f"| {label} | {part.value} | {cal}/{len(part.rows)} | "
                  + ", ".join(f"{v:.2f}" for v in z) + (" **out**" if bad_z else "") + " | "
                  + ", ".join(f"{v:.2f}" for v in plan) + (" **out**" if bad_p else "") + " | "
                  + ", ".join(f"{v:.3f}" for v in ps) + " |", flush=True)
    mean, lo, hi = chance_outside(counts)
    print(f"\n{n} cases: RMS error / sigma outside {BAND[0]}-{BAND[1]} on {off_z} (exact sigmas would put {mean:.1f} "
          f"there by chance, 5-95 % {lo}-{hi}); plan outside 25 % of the spread on {off_plan} ({args.trials} trials "
          f"each, cast anew); {refused} more refused in every trial")
    print(f"p_exact below {SIGNIFICANT} (of {4 * n}, {SIGNIFICANT * 4 * n:.1f} by chance): "
          + ("; ".join(significant) or "none"))
    print("RMS error / sigma over every case: " + ", ".join(
        f"{name} {math.sqrt(sum(v * v * k for v, k in rows) / max(sum(k for _, k in rows), 1)):.3f}"
        for name, rows in pooled.items()))
    if args.confirm > 0 and flagged:
        replicate(flagged, args.confirm, args.workers)


def replicate(flagged: dict[tuple[str, str], tuple[Scenario, list[str]]], trials: int, workers: int) -> None:
    """Each parameter below p = SUSPECT measured again on ``trials`` fresh trials of its case (seeds from
    CONFIRM_SEED on past the case's own, cast anew), judged on those alone at p = SIGNIFICANT: of the 156
    parameters, 7.8 fall below p = 0.05 and 1.6 below 0.01 by chance, and one chosen for being extreme says little
    about its sigma until fresh data show the same (a miss that is the sigma's replicates; one that was the draw
    does not). 96 trials also tell a sigma 1.25x off from an exact one (RMS 0.80: p 0.005)."""
    print(f"\nReplication: each parameter below p = {SUSPECT} on {trials} fresh trials (seeds from the case's "
          f"seed + {CONFIRM_SEED}), judged there at p = {SIGNIFICANT}")
    for (label, rho), (sc, names) in flagged.items():
        s = study(sc, trials, seed0=sc.seed + CONFIRM_SEED, workers=workers, recast=True,
                  vary=("sensor.noise_correlation", [float(rho)]))
        part = s.parts[0]
        st = part.stats()
        cal = sum(r.status == "calibrated" for r in part.rows)
        # where the checks refused some, the same trials forced as well: the RMS over all of them, unselected
        forced = (study(sc, trials, seed0=sc.seed + CONFIRM_SEED, workers=workers, recast=True, force=True,
                        vary=("sensor.noise_correlation", [float(rho)])).parts[0].stats()
                  if cal < len(part.rows) else None)
        for name in names:
            v, n = st[name]["rms_z"], int(st[name]["n"])
            pv = p_exact(v, n)
            verdict = "replicates: the sigma's" if pv < SIGNIFICANT else "does not replicate: the first was the draw"
            print(f"- {label} rho {rho} {name}: RMS error / sigma {v:.2f} over {n} calibrated of {cal}/"
                  f"{len(part.rows)} (p {pv:.4f}), plan {st[name]['rmse_over_predicted']:.2f}: {verdict}",
                  flush=True)
            if forced is not None:
                fv, fn = forced[name]["rms_z"], int(forced[name]["n"])
                print(f"  the same {len(part.rows)} trials with --force: {fv:.2f} over {fn} (p {p_exact(fv, fn):.4f})",
                      flush=True)


if __name__ == "__main__":
    main()
