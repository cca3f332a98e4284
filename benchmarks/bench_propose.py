"""The DH search (lrfcal.stages.propose, ``lrfcal inspect``'s proposal and the starts of the check "starts agree"):
its CPU and where it goes, and how far its proposal moves when only the draw of its segmentation subsamples
changes (issue 47).

    python benchmarks/bench_propose.py REC [REC ...] [--redraws 2]

Each recording (anything ``lrfcal inspect`` reads) is read as inspect reads it; the search then runs in this one
process (pinned to one core, so no start is forked; one BLAS thread), first as shipped, then ``--redraws`` times
with every start's segmentation subsample drawn afresh (numpy's generator seeded by the redraw and the start: the
same number of returns, nothing else changed). It also prints how many starts segment on another subsample than
start 0 as shipped (the search salts lrfcal.stages.sampling.hash_sample with 100 + k). Printed per run: the CPU of
the search, of its segmentations (lrfcal.stages.targetless.plane_returns_at) and of its solves
(lrfcal.estimate.solve.solve_planes); the proposal and its 1-sigma; and for the other draws, each value's change
from the shipped proposal in units of that proposal's 1-sigma. That change is the noise floor of the search: a
change of the search's arithmetic that moves a proposal by less is not distinguishable from a redraw.
"""

from __future__ import annotations

import argparse
import math
import os
import sys
import time
from collections.abc import Callable
from typing import Any

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import numpy as np  # noqa: E402

from lrfcal.commands.inspect_log import inspect_path  # noqa: E402
from lrfcal.estimate import solve  # noqa: E402
from lrfcal.stages import propose, targetless  # noqa: E402
from lrfcal.stages.sampling import hash_sample  # noqa: E402

NAMES = ("a", "alpha", "b", "beta")


def _timed(module: Any, name: str, spent: dict[str, float]) -> None:
    """``module.name`` replaced by a wrapper adding its CPU seconds to ``spent[name]``."""
    fn: Callable[..., Any] = getattr(module, name)

    def wrapper(*args: Any, **kwargs: Any) -> Any:
        t = time.process_time()
        try:
            return fn(*args, **kwargs)
        finally:
            spent[name] = spent.get(name, 0.0) + time.process_time() - t

    setattr(module, name, wrapper)


def _inputs(path: str) -> tuple[Any, Any]:
    """The scans and joint states the search gets from ``lrfcal inspect path`` (the search itself not run)."""
    got: list[tuple[Any, Any]] = []
    search = propose.propose_dh

    def keep(scans: Any, joints: Any, progress: Any = None) -> propose.DHProposal:
        got.append((scans, joints))
        return propose.DHProposal(None, reason="not searched")

    propose.propose_dh = keep
    try:
        inspect_path(path)
    finally:
        propose.propose_dh = search
    if not got:
        sys.exit(f"{path}: inspect did not reach the search (see `lrfcal inspect {path}`)")
    return got[0]


def _redrawn(redraw: int) -> Callable[..., Any]:
    """A stand-in for hash_sample in the search: a fresh subsample per (redraw, start), in the returns' order."""

    def draw(scan: Any, beam: Any, n: int, seed: int = 0) -> Any:
        k = len(scan)
        if n >= k:
            return np.arange(k)
        return np.sort(np.random.default_rng([redraw, seed]).choice(k, n, replace=False))

    return draw


def _distinct_subsamples(scans: Any) -> int:
    """How many of the search's starts segment on another subsample than start 0 (as shipped)."""
    beams = targetless.sample_returns(scans, propose.FIT_RETURNS)
    first = hash_sample(beams.scan, beams.beam, propose.SEGMENT_RETURNS, seed=100)
    return sum(not np.array_equal(first, hash_sample(beams.scan, beams.beam, propose.SEGMENT_RETURNS, seed=100 + k))
               for k in range(1, 12))


def _row(p: propose.DHProposal) -> str:
    if p.dh is None:
        return f"no proposal: {p.reason}"
    v = p.values() or {}
    return (f"{p.n_agreeing}/{p.n_starts} agree; " + ", ".join(
        f"{n} {v[n]:+.4f} +-{p.sigma[n]:.4f}" for n in NAMES))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("recordings", nargs="+")
    ap.add_argument("--redraws", type=int, default=2, help="runs with fresh segmentation subsamples")
    args = ap.parse_args()
    if hasattr(os, "sched_setaffinity"):
        os.sched_setaffinity(0, {min(os.sched_getaffinity(0))})  # one core: lrfcal.runtime.forked forks nothing
    spent: dict[str, float] = {}
    _timed(targetless, "plane_returns_at", spent)
    _timed(solve, "solve_planes", spent)
    for path in args.recordings:
        scans, joints = _inputs(path)
        print(f"{path}: {scans.ranges_m.shape[0]} scans; starts 1-11 segmenting on another subsample than start 0: "
              f"{_distinct_subsamples(scans)}")
        base: propose.DHProposal | None = None
        for redraw in range(args.redraws + 1):
            if redraw:
                propose.hash_sample = _redrawn(redraw)  # type: ignore[assignment]
            spent.clear()
            t = time.process_time()
            try:
                p = propose.propose_dh(scans, joints)
            finally:
                propose.hash_sample = hash_sample  # type: ignore[assignment]
            cpu = time.process_time() - t
            run = f"redraw {redraw}" if redraw else "shipped"
            line = (f"  {run}: CPU {cpu:.2f} s (segmentations {spent.get('plane_returns_at', 0.0):.2f}, "
                    f"solves {spent.get('solve_planes', 0.0):.2f}); {_row(p)}")
            if base is None:
                base = p
            elif base.dh is not None and p.dh is not None:
                b, d = base.dh.vector(), p.dh.vector()
                moved = [abs(float(d[i] - b[i])) / base.sigma[n] for i, n in enumerate(NAMES)]
                if abs(d[3] - b[3]) > math.pi:  # beta wrapped
                    moved[3] = float("nan")
                line += "; moved " + ", ".join(f"{n} {m:.2f}" for n, m in zip(NAMES, moved, strict=True)) + " sigma"
            print(line, flush=True)


if __name__ == "__main__":
    main()
