"""One estimate over observation sets: the robust passes and the covariance, written once.

:func:`estimate` takes a problem of observation sets (lrfcal.estimate.problem.Problem, each set an
lrfcal.model.observations.ObservationSet), a start (:class:`State`) and the unknowns (:class:`Unknowns`: which are
free, which are held and why), and returns a typed :class:`Estimate`:

1. the robust passes (:class:`Passes`): a Huber-weighted pass (threshold 2 sigma) from the start, then plain least
   squares with each set's returns beyond 4 robust sigma left out (each set's own rule,
   ObservationSet.kept), every set chosen again at each new estimate (ObservationSet.chosen_at: the markers crossed
   on both sides), repeated until the kept sets are stable; a plane set's range pattern along the scan
   (lrfcal.model.range_pattern) is held in these passes and estimated in one more pass over the kept returns;
2. the covariance at the solution (lrfcal.estimate.covariance.uncertainty): s^2 (J^T J)^-1 with its
   cluster-robust widening (each set's clusters, ObservationSet.clusters; its groups, ObservationSet.groups), the
   marker map's own uncertainty, and the score tests of unknowns held by default.

Each pass is Levenberg-Marquardt on the normal equations (lrfcal.estimate.normal_equations), the planes' nuisances
eliminated by the Schur complement; with the mount and every DH parameter free and no prior on them, the scan plane
moves in the regular chart (lrfcal.model.chart), the gauge into the mount after every step.

:func:`solved` is how a calibration's solves reach the engine: a request (lrfcal.estimate.request: what to estimate,
built by the stages) posed and estimated, its estimate reported as a Solution. The orchestrator (lrfcal.pipeline)
calls it for every start and every set chosen again, and the checks that solve again (lrfcal.estimate.checks,
minima) call it themselves.
"""

from __future__ import annotations

import enum
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from functools import partial
from typing import Protocol

import numpy as np
from numpy.typing import NDArray

from lrfcal.estimate.covariance import Covariance, held_score, uncertainty
from lrfcal.estimate.normal_equations import Limits, assemble, levenberg_marquardt, schur
from lrfcal.estimate.problem import Problem
from lrfcal.model.chart import regular_chart_at, regular_step
from lrfcal.model.kinematics import exp_so3
from lrfcal.model.unknowns import CORE_NAMES, N_CORE, UNKNOWNS
from lrfcal.types import Iteration, Solution

FloatArray = NDArray[np.float64]
BoolArray = NDArray[np.bool_]
IntArray = NDArray[np.int64]


class Status(enum.Enum):
    """How the last plain pass ended (as mujoco's ``minimize.Status``)."""

    CONVERGED = "converged"
    MAX_ITER = "maximum number of iterations reached"


class Stop(enum.Enum):
    """When the robust passes stop on a kept set that no longer changes.

    AFTER_REFIT: a plain pass on the set found unchanged, then stop (the marker returns' passes: the set was chosen
    at the previous estimate, so one more pass on it is the solution); BEFORE_REFIT: stop as soon as the set is the
    one the last plain pass was on (the targetless passes: that pass is the solution)."""

    AFTER_REFIT = "after"
    BEFORE_REFIT = "before"


@dataclass(frozen=True)
class Passes:
    """The robust passes of one call: robust (False: one plain pass), the Huber pass first, the most rounds of
    rejection, when to stop on an unchanged set (:class:`Stop`), a last plain pass when the rounds ended on a
    changed set, and each pass's Levenberg-Marquardt limits (iterations; steps below ``step_tol`` of their sigma
    converge)."""

    robust: bool = True
    huber_first: bool = True
    rounds: int = 5
    stop: Stop = Stop.AFTER_REFIT
    last_refit: bool = True
    max_iter: int = 100
    step_tol: float = 1e-2


#: the marker returns' passes (lrfcal.estimate.request.MarkerRequest): steps below 1e-2 sigma converge (the clock
#: offset's Jacobian, a smoothed joint velocity, makes the last iterations converge only linearly)
MARKER_PASSES = Passes()
#: the targetless passes (lrfcal.estimate.request.PlaneRequest)
PLANE_PASSES = Passes(rounds=6, stop=Stop.BEFORE_REFIT, last_refit=False, max_iter=60, step_tol=1e-3)


@dataclass(frozen=True)
class State:
    """The unknowns: th (N_CORE + nuisances,) (the mount's rotation a small rotation vector th[3:6] applied to R_ref)
    and R_ref (3, 3)."""

    th: FloatArray
    R_ref: FloatArray


@dataclass(frozen=True)
class Unknowns:
    """Which unknowns are estimated: free (N_CORE + nuisances,), and each held core unknown's reason (name -> why)."""

    free: BoolArray
    held: Mapping[str, str]

    @classmethod
    def of(cls, free_core: BoolArray, n_nuisance: int, why: Mapping[str, str]) -> Unknowns:
        """Free core unknowns (N_CORE,) and every nuisance; each held one with its reason from ``why``, else the
        model's table's (lrfcal.model.unknowns.UNKNOWNS: why it is held by default)."""
        free = np.concatenate([np.asarray(free_core, dtype=bool), np.ones(n_nuisance, dtype=bool)])
        held = {u.name: why.get(u.name) or u.held or "held by the call"
                for u, f in zip(UNKNOWNS, free_core, strict=True) if not f}
        return cls(free, held)


@dataclass(frozen=True)
class Estimate:
    """One estimate: the state, the problem as last chosen (all returns), which returns of each set were kept, how
    the last pass ended, the evaluations of all passes, each accepted iteration of every pass, and the covariance at
    the solution with the score tests of held unknowns (lrfcal.estimate.covariance.uncertainty, held_score)."""

    state: State
    problem: Problem
    keep: tuple[BoolArray, ...]
    status: Status
    n_evaluations: int
    log: tuple[Iteration, ...]
    uncertainty: Covariance

    @property
    def kept(self) -> Problem:
        """The problem of the kept returns."""
        return self.problem.subset(self.keep)


def _pass(state: State, pb: Problem, free: BoolArray, passes: Passes, huber: bool, log: list[Iteration]
          ) -> tuple[State, int, Status]:
    """One solver pass over the free unknowns (Huber weights at 2 sigma, or plain least squares); the rotation
    increment folded into R_ref after it. In the regular chart when the mount and every DH parameter are free and
    no prior holds the DH chart (lrfcal.model.chart)."""
    regular = pb.mount_jac and pb.dh_prior is None and bool(free[:10].all())
    R_ref = state.R_ref
    th, nfev, ok = levenberg_marquardt(
        state.th, lambda x, j: pb.blocks(x, R_ref, j, chart=regular_chart_at(x) if regular else None),
        np.flatnonzero(free[:N_CORE]), N_CORE, huber=2.0 if huber else None,
        limits=Limits(passes.max_iter, passes.step_tol), retract=regular_step(R_ref) if regular else None, log=log)
    R_new = R_ref @ exp_so3(th[3:6])
    th[3:6] = 0.0
    return State(th, R_new), nfev, Status.CONVERGED if ok else Status.MAX_ITER


def _robust_passes(pb: Problem, start: State, free: BoolArray, passes: Passes, log: list[Iteration]
                   ) -> tuple[State, Problem, tuple[BoolArray, ...], int, Status]:
    """The passes of :func:`estimate`: returns the state, the problem as last chosen, the kept returns per set,
    the evaluations and the last plain pass's status."""
    state, nfev, status = start, 0, Status.CONVERGED
    keep = tuple(np.ones(s.size, dtype=bool) for s in pb.sets)
    # which returns count is judged with the range pattern along the scan held (lrfcal.model.range_pattern): free,
    # it takes up what the same beams see at every tilt (the room replica's stand base, 2 cm above the desk, became
    # the desk: no longer a plane far thicker than the others, a and b 5-8 cm off); the estimate is the cost with
    # the pattern over the returns that count, after the rounds
    with_pattern, pb = pb, pb.without_pattern()
    if passes.robust and passes.huber_first:
        state, nfev, _ = _pass(state, pb, free, passes, True, log)
    changed, fitted = True, False
    for _ in range(passes.rounds if passes.robust else 0):
        pb = pb.chosen_at(state.th, state.R_ref)
        new = pb.kept(state.th, state.R_ref, keep)
        if any(int(n.sum()) < s.min_kept for s, n in zip(pb.sets, new, strict=True)):
            break
        changed = not all(np.array_equal(n, k) for n, k in zip(new, keep, strict=True))
        if passes.stop is Stop.BEFORE_REFIT and fitted and not changed:
            break
        keep = new
        state, nf, status = _pass(state, pb.subset(keep), free, passes, False, log)
        nfev, fitted = nfev + nf, True
        if passes.stop is Stop.AFTER_REFIT and not changed:
            break
    if not passes.robust or (passes.last_refit and changed):
        pb = pb.chosen_at(state.th, state.R_ref)
        state, nf, status = _pass(state, pb.subset(keep), free, passes, False, log)
        nfev += nf
    if with_pattern.has_pattern:
        pb = with_pattern.chosen_at(state.th, state.R_ref)
        state, nf, status = _pass(state, pb.subset(keep), free, passes, False, log)
        nfev += nf
    return state, pb, keep, nfev, status


def _uncertainty(pb: Problem, state: State, free: BoolArray, map_cov: FloatArray | None,
                 held_scores: Sequence[str]) -> Covariance:
    """The covariance of the kept problem ``pb`` at ``state`` with its sets' clusters and groups
    (Problem.clusters), and the score tests of ``held_scores``."""
    unc = partial(uncertainty, pb, R_ref=state.R_ref, map_cov=map_cov)
    at_solution = pb.blocks(state.th, state.R_ref)  # the residuals and Jacobian at the solution, once for both
    at = unc(th=state.th, free=free, blocks=at_solution)
    score = held_score(pb, state.th, state.R_ref, free, at.reduced_chi2, unc, held_scores, blocks=at_solution)
    return at._replace(held_score=score)


def estimate(pb: Problem, start: State, unknowns: Unknowns, passes: Passes = MARKER_PASSES, *,
             map_cov: FloatArray | None = None, held_scores: Sequence[str] = ()) -> Estimate:
    """The estimate of the free ``unknowns`` from the observation sets of ``pb`` (all returns), from ``start``:
    the robust passes (``passes``) and the covariance at the solution (module docstring). ``map_cov`` (3n, 3n): the
    marker map's own uncertainty, carried through the solution; ``held_scores``: unknowns held by default whose
    score test to run (lrfcal.estimate.covariance.held_score)."""
    log: list[Iteration] = []
    state, pb, keep, nfev, status = _robust_passes(pb, start, unknowns.free, passes, log)
    unc = _uncertainty(pb.subset(keep), state, unknowns.free, map_cov, held_scores)
    return Estimate(state, pb, keep, status, nfev, tuple(log), unc)


class Posed(Protocol):
    """A request as the engine takes it (lrfcal.estimate.request): the problem, the start, the unknowns, the passes,
    the marker map's covariance and the score tests to run, and how the estimate is reported as a Solution."""

    @property
    def problem(self) -> Problem: ...
    @property
    def start(self) -> State: ...
    @property
    def unknowns(self) -> Unknowns: ...
    @property
    def passes(self) -> Passes: ...
    @property
    def map_cov(self) -> FloatArray | None: ...
    @property
    def held_scores(self) -> Sequence[str]: ...
    def solution(self, est: Estimate) -> Solution: ...


class Request(Protocol):
    """What to estimate (lrfcal.estimate.request.MarkerRequest, PlaneRequest): posed to the engine on demand (posing
    may refuse it: CalibrationError)."""

    def posed(self) -> Posed: ...


def solved(request: Request) -> Solution:
    """The estimate of one request (:func:`estimate` on it, reported as its Solution): how every solve of a
    calibration reaches the engine. Raises CalibrationError where the request cannot be posed (too few returns)."""
    p = request.posed()
    return p.solution(estimate(p.problem, p.start, p.unknowns, p.passes, map_cov=p.map_cov,
                               held_scores=p.held_scores))


def information(pb: Problem, state: State, core: IntArray) -> tuple[FloatArray, tuple[str, ...]]:
    """What the observation sets of ``pb`` determine at ``state`` without iterating: the information (k, k) over the
    core unknowns ``core`` (indices into CORE_NAMES), every set's nuisances marginalised (the Schur complement of the
    normal equations the passes solve), and their names."""
    S, _, _ = schur(assemble(pb.blocks(state.th, state.R_ref), core))
    return S, tuple(CORE_NAMES[k] for k in core)


__all__ = ["MARKER_PASSES", "PLANE_PASSES", "Estimate", "Passes", "Posed", "Request", "State", "Status", "Stop",
           "Unknowns", "estimate", "information", "solved"]
