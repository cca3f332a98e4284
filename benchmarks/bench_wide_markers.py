"""Are the markers of the broad random truths actually seen? (lrfsim.testing.random_scenarios.random_scenario_wide)

    python benchmarks/bench_wide_markers.py [N_SEEDS=60] [FIRST_SEED=0]

Per seed: simulate (one at a time), detect intensity blobs (lrfcal.stages.detection.detect) and count the markers
with a detected blob on their returns (lrfsim.simulation.faults.marker_returns attributes returns to markers with the
truth), against the markers the sweep can see by geometry (visible_markers) and the layout's
wide_dh_determined label. Prints one line per seed, then the fraction of scenarios with fewer than 6 markers
detected (target: small; measured 0 of 60 at commit time) and the fraction labelled determined.
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from lrfsim.simulation.simulate import simulate
from lrfsim.testing.random_scenarios import detected_markers, random_scenario_wide, visible_markers, wide_dh_determined

MIN_SEEN = 6


def markers_detected(seed: int) -> tuple[str, int, int, int, bool, float]:
    """(name, markers detected, visible by geometry, markers in all, determined label, seconds)."""
    sc = random_scenario_wide(seed)
    t0 = time.perf_counter()
    seen = detected_markers(simulate(sc), sc)
    vis = visible_markers(sc)
    return sc.name, len(seen), int(vis.sum()), int(vis.size), wide_dh_determined(sc), time.perf_counter() - t0


def main(n_seeds: int, first: int) -> None:
    rows = []
    for seed in range(first, first + n_seeds):
        name, seen, vis, n, determined, secs = markers_detected(seed)
        rows.append((seen, determined))
        print(f"{seed:4d} {name:40s} detected {seen:2d}  visible {vis:2d} of {n:2d}  "
              f"{'determined' if determined else 'weak':10s} {secs:5.1f} s", flush=True)
    seen_arr = np.array([r[0] for r in rows])
    print(f"fewer than {MIN_SEEN} markers detected: {int((seen_arr < MIN_SEEN).sum())} of {len(rows)} "
          f"({100 * np.mean(seen_arr < MIN_SEEN):.1f} %); labelled determined: "
          f"{100 * np.mean([r[1] for r in rows]):.0f} %")


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__.split("\n", 1)[0])
    parser.add_argument("n_seeds", nargs="?", type=int, default=60, help="scenarios to draw (default 60)")
    parser.add_argument("first_seed", nargs="?", type=int, default=0, help="the first seed (default 0)")
    args = parser.parse_args()
    main(args.n_seeds, args.first_seed)
