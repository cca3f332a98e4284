"""The method's loop, the same for both ways (lrfcal.stages.markers.MarkerWay, lrfcal.stages.scene.PlaneWay): a way
supplies what varies (its observation sets, its candidate starts, how it chooses among their estimates and asks for
further ones, how it chooses the sets again at a new estimate, its systematic errors, its checks); this loop owns what
is common and calls the engine (lrfcal.estimate.engine.solved) itself, on what the way asks to estimate:

    observed, starts = way.observe(proposal)
    tried = [estimate from each start, its sets chosen again until they stand]
    while the way's choice asks for further starts: tried += [estimate from each]
    best = the choice, its sets chosen again until they stand
    widened = the covariance widened by the way's systematics (lrfcal.estimate.systematics, one place)
    result = way.checks(observed, best, widened, the methods beside)

Several starts at once run on the machine's cores (forked children, lrfcal.runtime.forked), collected in start order:
what runs in other processes is arranged here, outside the way's steps.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from functools import partial
from typing import Protocol, TypeVar

import numpy as np

from lrfcal.errors import CalibrationError
from lrfcal.estimate.engine import solved
from lrfcal.estimate.request import Request
from lrfcal.estimate.systematics import Systematics, widened
from lrfcal.result import CalibrationResult
from lrfcal.runtime.forked import call_forked, cores
from lrfcal.stages.propose import Proposal
from lrfcal.types import Fit, Noted, Solution, Tried

Ob = TypeVar("Ob")  # what a way observed
St = TypeVar("St")  # its candidate starts
S = TypeVar("S")  # its observation sets as chosen


class Way(Protocol[Ob, St, S]):
    """A way of calibrating: what varies between the ways, as the steps :func:`estimated` calls (a way keeps no state
    between them: what a later step needs travels in what an earlier one returned).

    ``observe``: the observation sets and the first candidate starts (``proposal``: the DH search's proposal, begun
    ahead where the way's ``SEARCH`` asks for it, else None); ``sets_at``: the sets at a start; ``problem``: what to
    estimate on sets (lrfcal.estimate.request); ``reselect``: the sets chosen again at an estimate (sets to solve, a
    Fit where the estimate stands on sets chosen again, None where they stand); ``choose``: the fit chosen among
    those of the starts tried, or the further starts the choice needs; ``systematics``: what to widen the chosen
    estimate's covariance by; ``beside``: the methods run beside it for comparison; ``checks``: the result without
    clouds. The two ways: ``Way[markers.Observed, alternatives.Start, marker_sets.MarkerSets]`` and
    ``Way[scene.Scene, starts.PlaneStart, starts.PlaneSets]``, checked by mypy (tests/static_types.py)."""

    def observe(self, proposal: Proposal | None) -> tuple[Ob, Sequence[St]]: ...
    def sets_at(self, observed: Ob, start: St) -> S: ...
    def problem(self, observed: Ob, sets: S) -> Request: ...
    def reselect(self, observed: Ob, fit: Fit[S]) -> S | Fit[S] | None: ...
    def choose(self, observed: Ob, tried: Sequence[Tried[St, S]]) -> Fit[S] | Sequence[St]: ...
    def systematics(self, observed: Ob, best: Fit[S]) -> Systematics: ...
    def beside(self, observed: Ob, best: Fit[S]) -> Mapping[str, Request]: ...
    def checks(self, observed: Ob, best: Fit[S], widened: Noted[Solution],
               beside: Mapping[str, Solution | CalibrationError]) -> CalibrationResult: ...


def estimated(way: Way[Ob, St, S], proposal: Proposal | None) -> CalibrationResult:
    """The way's result without clouds: its starts estimated, the choice among them, its sets chosen again until
    they stand, its covariance widened by its systematics, its checks (module docstring)."""
    observed, starts = way.observe(proposal)
    tried = _tried(way, observed, starts)
    while not isinstance(chosen := way.choose(observed, tried), Fit):
        tried = [*tried, *_tried(way, observed, chosen)]
    best = _reselected(way, observed, chosen)
    systematics = way.systematics(observed, best)
    variants = [_solved_or(error.variant) for error in systematics.model_errors]
    widest = widened(best.solution, systematics, [v if isinstance(v, Solution) else None for v in variants])
    beside = {name: _solved_or(request) for name, request in way.beside(observed, best).items()}
    return way.checks(observed, best, widest, beside)


def _reselected(way: Way[Ob, St, S], observed: Ob, fit: Fit[S]) -> Fit[S]:
    """``fit`` with its sets chosen again at each new estimate until they stand, each solved."""
    while (again := way.reselect(observed, fit)) is not None:
        fit = again if isinstance(again, Fit) else Fit(again, solved(way.problem(observed, again)))
    return fit


def _tried(way: Way[Ob, St, S], observed: Ob, starts: Sequence[St]) -> list[Tried[St, S]]:
    """Each start estimated (:func:`_from`), several on the machine's cores (every n-th in one child), in start
    order."""
    n = max(1, min(cores(), len(starts)))
    if n == 1:
        return [_from(way, observed, start) for start in starts]
    done = call_forked({str(g): partial(_from_each, way, observed, starts[g::n]) for g in range(n)})
    return [done[str(i % n)][i // n] for i in range(len(starts))]


def _from_each(way: Way[Ob, St, S], observed: Ob, starts: Sequence[St]) -> list[Tried[St, S]]:
    return [_from(way, observed, start) for start in starts]


def _from(way: Way[Ob, St, S], observed: Ob, start: St) -> Tried[St, S]:
    """The estimate from one start, its sets chosen again until they stand, or the refusal that ended it (the way's
    choice judges it)."""
    try:
        sets = way.sets_at(observed, start)
        return Tried(start, _reselected(way, observed, Fit(sets, solved(way.problem(observed, sets)))))
    except (CalibrationError, np.linalg.LinAlgError) as err:
        return Tried(start, err)


def _solved_or(request: Request) -> Solution | CalibrationError:
    """A request beside the estimate solved, or why it could not be."""
    try:
        return solved(request)
    except CalibrationError as err:
        return err


__all__ = ["Way", "estimated"]
