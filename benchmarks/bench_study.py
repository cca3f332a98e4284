"""Study benchmark (issue 10): the statistical efficiency of the whole method, and what a Monte-Carlo trial costs.

For each scenario (default tunnel_v and plane_30deg), N trials (default 100, seeds 100..199) of ``lrfsim study``
(new noise per trial, one noise-free cast reused; ``--recast`` casts every trial anew, a new laser phase, so that
the bias is averaged over where the beams fall on the 5 mm markers, not only over the noise; ``--perturb-start S``
also moves each trial's nominal values)
and the prediction of ``lrfsim plan``; prints per DH parameter:
  - predicted sigma (Fisher information of the noise-free geometry) and the Monte-Carlo std, and their ratio
    (target: the prediction within +-25 % of the std, i.e. std / predicted in 0.75-1.25; with N trials the std
    itself is known to about +-1 / sqrt(2 N), 7 % at N = 100);
  - RMSE / predicted sigma (the efficiency);
  - RMS of error / reported sigma (target 0.8-1.25);
  - the bias (mean error) with its standard error std / sqrt(N), and bias / std (target |bias| < 0.3 std; its
    standard error is 1 / sqrt(N), 0.1 at N = 100: N = 30 cannot tell 0.3 from 0);
and the refusal rate; every missed target is named. Then the cost: a full simulation, a trial's simulation on the
reused cast (the ratio, target <= 0.3), a whole trial (simulate + write + read + calibrate), and trials per minute
on the workers used.

    python benchmarks/bench_study.py [--trials 100] [--workers 1] [--scenarios tunnel_v plane_30deg FILE.yaml]
                                     [--recast | --new-layout [--jitter M]] [--perturb-start S] [-o DIR]

``--new-layout --jitter M`` moves every marker of a V or a board by up to M per trial (the layout's jitter_m):
the markers a user places by hand are never where a drawing puts them, and the reported sigma covers where the
beams fall on them, which only a new layout per trial draws anew.
"""

from __future__ import annotations

import argparse
import math
import tempfile
import time
from pathlib import Path

from lrfcal.model.kinematics import DH_NAMES
from lrfsim.plan.result import format_value
from lrfsim.scenario.file import Scenario, load_scenario
from lrfsim.simulation.simulate import cast_geometry, simulate, simulate_from_geometry
from lrfsim.trials.study import study
from lrfsim.trials.study_result import write_study
from lrfsim.trials.variants import with_field

ROOT = Path(__file__).resolve().parents[1]


def _load(name: str, jitter_m: float | None = None) -> Scenario:
    """A shipped scenario by name (scenarios/NAME.yaml), else a scenario file (e.g. benchmarks/layouts/*.yaml);
    with ``jitter_m``, its V or board layout's jitter set to it."""
    shipped = ROOT / "scenarios" / f"{name}.yaml"
    sc = load_scenario(shipped if shipped.is_file() else Path(name))
    return sc if jitter_m is None else with_field(sc, "markers.layout.jitter_m", jitter_m)


def _cost(name: str) -> tuple[float, float]:
    """(seconds of a full simulation, seconds of a noise-only simulation on a reused cast)."""
    sc = _load(name)
    t = time.perf_counter()
    simulate(sc)
    full = time.perf_counter() - t
    geometry = cast_geometry(sc)
    t = time.perf_counter()
    simulate_from_geometry(sc.model_copy(update={"seed": sc.seed + 1}), geometry)
    return full, time.perf_counter() - t


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--trials", type=int, default=100)
    ap.add_argument("--workers", type=int, default=1)
    ap.add_argument("--seed0", type=int, default=100)
    ap.add_argument("--scenarios", nargs="+", default=["tunnel_v", "plane_30deg"])
    ap.add_argument("--recast", action="store_true",
                    help="cast every trial anew (lrfsim study --recast): the bias over laser phases, not one cast's")
    ap.add_argument("--new-layout", action="store_true",
                    help="also a new marker layout per trial (lrfsim study --new-layout): the bias over layouts")
    ap.add_argument("--jitter", type=float, default=None, metavar="M",
                    help="the V's or board's jitter_m [m] (with --new-layout: each trial's markers moved by up to M)")
    ap.add_argument("--perturb-start", type=float, default=0.0, metavar="S",
                    help="move each trial's nominal values (lrfsim.trials.study.perturbed_start; 0: off)")
    ap.add_argument("-o", "--out", type=Path, default=None, help="keep each study's folder here (DIR/<scenario>)")
    args = ap.parse_args()
    missed: list[str] = []
    for name in args.scenarios:
        sc = _load(name, args.jitter)
        full, noise = _cost(name)
        t0 = time.perf_counter()
        s = study(sc, args.trials, seed0=args.seed0, workers=args.workers, perturb_start=args.perturb_start,
                  recast=args.recast, new_layout=args.new_layout)
        wall = time.perf_counter() - t0
        part = s.parts[0]
        st = part.stats()
        n_cal = int(st["a"]["n"])
        start = f", start perturbed x{args.perturb_start:g}" if args.perturb_start > 0 else ""
        start += (", a new layout per trial" if args.new_layout else ", every trial cast anew" if args.recast
                  else ", one cast reused")
        print(f"\n{name}: {n_cal}/{len(part.rows)} calibrated (refusal rate {100 * part.refusal_rate:.0f} %), "
              f"seeds {args.seed0}..{args.seed0 + args.trials - 1}{start}, {args.workers} worker(s), {wall:.0f} s, "
              f"{60 * len(part.rows) / wall:.1f} trials per minute")
        print(f"  {'param':<6}{'predicted':>12}{'MC std':>12}{'std/pred':>10}{'RMSE/pred':>11}{'RMS z':>8}"
              f"{'bias +- s.e.':>26}{'bias/std':>10}{'+-':>6}")
        for p in DH_NAMES:
            d = st[p]
            se = 1 / math.sqrt(max(n_cal, 1))
            bias = f"{format_value(p, d['bias'])} +- {format_value(p, d['bias_se'])}"
            bz = d["bias"] / d["std"]
            print(f"  {p:<6}{format_value(p, d['predicted']):>12}{format_value(p, d['std']):>12}"
                  f"{d['std_over_predicted']:>10.2f}{d['rmse_over_predicted']:>11.2f}{d['rms_z']:>8.2f}"
                  f" {bias:>25}{bz:>+10.2f}{se:>6.2f}")
            if not 0.75 <= d["std_over_predicted"] <= 1.25:
                missed.append(f"{name} {p}: std / predicted {d['std_over_predicted']:.2f} (target 0.75-1.25)")
            if not 0.8 <= d["rms_z"] <= 1.25:
                missed.append(f"{name} {p}: RMS of error / reported sigma {d['rms_z']:.2f} (target 0.8-1.25)")
            if not abs(bz) < 0.3:
                missed.append(f"{name} {p}: bias / std {bz:+.2f} +- {se:.2f} (target |bias / std| < 0.3)")
        for r in part.rows:
            if r.status != "calibrated":
                print(f"  refused trial {r.trial} (seed {r.seed}): {r.reason}")
        mean_trial = sum(r.seconds for r in part.rows) / max(len(part.rows), 1)
        print(f"  cost: full simulation {full:.2f} s; noise-only simulation on the reused cast {noise:.3f} s "
              f"(ratio {noise / full:.3f}, target <= 0.3); calibration {mean_trial:.1f} s per trial; "
              f"a whole trial {wall / len(part.rows):.1f} s of wall time on {args.workers} worker(s)")
        if args.out is not None:
            print(f"  wrote {write_study(s, args.out / sc.name, overwrite=True)}")
        else:
            with tempfile.TemporaryDirectory() as tmp:
                write_study(s, Path(tmp) / sc.name)
    print("\nall targets met" if not missed else "\ntargets missed:\n  " + "\n  ".join(missed))


if __name__ == "__main__":
    main()
