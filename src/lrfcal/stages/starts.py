"""Targetless: every start the data allow minimises the one cost, and the lowest minimum is the estimate (issue 46, 54).

The plane solve is local: where the scene's planes hardly constrain a parameter, a solve stops wherever it started,
and the sigma of the result (the curvature at that point) does not show it. So the targetless cost (the planes and
their returns segmented once, at the rig file's DH: lrfcal.stages.targetless) is minimised from every start the
recording allows: the rig file's DH (the nominal), the proposal of the DH search (lrfcal.stages.propose: inspect's
proposal, the median of the search's agreeing starts) and the agreeing starts themselves, the ones farthest from the
nominal's minimum first (at most :data:`MAX_OTHER_STARTS`). Every start minimises the same function: the same
returns on the same planes, the same parameters held at the nominal, the same prior around the nominal and clock;
only where the solve starts differs. Each is first brought to the chain's twin nearest the nominal
(lrfcal.model.kinematics.dh_twins: flatness cannot tell them apart). A start closer to the nominal's minimum than
:data:`AGREE_SIGMA` of its sigma on every estimated parameter is not run (it would test nothing).

The estimate is the minimum of lowest cost (lrfcal.estimate.minima.plane_cost: the planes fitted afresh at each
minimum's DH, the same truncated squares for all). Every other minimum more than :data:`AGREE_SIGMA` of the
estimate's 1-sigma from it on an estimated parameter is judged by the likelihood-ratio rule the marker calibration's
"other minimum" uses (lrfcal.estimate.checks.judge_minima): a minimum that fits clearly worse is a local one
(passed); one that fits about as well is a second rig the scene's planes cannot tell from the estimate, and the
check "starts agree" fails naming the parameters on which they differ: the scene does not determine them.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import TypeVar

import numpy as np
from numpy.typing import NDArray

from lrfcal.errors import CalibrationError
from lrfcal.estimate import minima, observability
from lrfcal.estimate.checks import LR_LIMIT, judge_minima
from lrfcal.model.kinematics import DH, dh_twins
from lrfcal.model.motor import MotorClock
from lrfcal.model.unknowns import dh_difference
from lrfcal.stages import propose, targetless
from lrfcal.types import Check, Fit, Solution, Tried

FloatArray = NDArray[np.float64]
S = TypeVar("S")
DH_NAMES = observability.DH
#: other minima within this many of the estimate's 1-sigma of it, on every estimated DH parameter, are the same one
AGREE_SIGMA = 1.0
#: the other starts run at most (the proposal first, then the agreeing starts farthest from the nominal's minimum)
MAX_OTHER_STARTS = 2
NAME = "starts agree"
#: the scales [m, rad, m, rad] on which a candidate's twin nearest the nominal is chosen (1 cm ~ 0.1 rad)
TWIN_SCALE = np.array([0.01, 0.1, 0.01, 0.1])


@dataclass(frozen=True)
class PlaneStart:
    """A start of the targetless cost: its name ("the rig file's DH", "the DH search's proposal", "the DH search's
    agreeing start 1", ...), its DH (the clock offset at the calibration's start) and the DH parameters held at the
    nominal beyond the scene's, judged at an estimate from it (lrfcal.stages.scene.PlaneWay.reselect)."""

    name: str
    dh: DH
    held: tuple[str, ...] = ()


NOMINAL = "the rig file's DH"


@dataclass(frozen=True)
class PlaneSets:
    """The targetless cost's sets at a start (the plane returns and their planes are the scene's, fixed: only the
    start differs) and, once chosen, the check "starts agree" that came with the choice (:func:`lowest`)."""

    start: PlaneStart
    agree: Check | None = None


@dataclass(frozen=True)
class Minima:
    """The targetless cost minimised from every start: the estimate (the lowest cost), its start and the check
    "starts agree"."""

    solution: Solution
    start: PlaneStart
    check: Check


@dataclass(frozen=True)
class Cost:
    """What the cost of a minimum is evaluated on (lrfcal.estimate.minima.plane_cost): the fixed plane returns, the
    motor clock, the range noise [m] and the design drawing's prior on the DH ((4,) mean and sigma)."""

    segmented: targetless.Segmented
    motor: MotorClock
    range_sigma_m: float
    prior: tuple[FloatArray, FloatArray]

    def __call__(self, sol: Solution, scale: float) -> float:
        return minima.plane_cost(self.segmented.returns, sol, self.motor, self.range_sigma_m * scale, self.prior)


def searched(proposal: propose.Proposal | None) -> propose.DHProposal:
    """The DH search's proposal (begun ahead, lrfcal.pipeline.search), or why there is none (None: not searched)."""
    if proposal is None:
        return propose.DHProposal(None, reason="not searched")
    try:
        return proposal()
    except (CalibrationError, np.linalg.LinAlgError) as err:
        return propose.DHProposal(None, reason=str(err))


def further(first: Solution, found: propose.DHProposal, held: tuple[str, ...], nominal: DH) -> list[PlaneStart]:
    """The other starts to minimise the cost from, beside the nominal's minimum ``first`` (module docstring): the
    search's proposal and its agreeing starts ``found``, each as the twin nearest the nominal, without those within
    AGREE_SIGMA of ``first`` or of another on every estimated parameter (``held``: the others), at most
    MAX_OTHER_STARTS."""
    if found.dh is None:
        return []
    est = [k for k, n in enumerate(DH_NAMES) if n not in held]
    return [PlaneStart(_start_name(i), dh)
            for i, dh in enumerate(_other_starts([found.dh, *found.agreeing], nominal, first, est))]


def lowest(tried: Sequence[Tried[PlaneStart, S]], cost: Callable[[Solution, float], float],
           held: tuple[str, ...], found: propose.DHProposal) -> Minima:
    """The targetless cost's minimum of lowest cost among the starts ``tried`` (the nominal's first, then those
    :func:`further` gave) and the check "starts agree": another start's minimum is the estimate only where it fits
    clearly better than the nominal's (lrfcal.estimate.checks.LR_LIMIT) and lies apart from it; every other minimum
    apart from the estimate is judged by the likelihood-ratio rule. ``cost(minimum, scale)``: the cost on the fixed
    plane returns (:class:`Cost`); ``found``: the DH search's outcome the other starts came from.

    Raises:
        CalibrationError: the nominal's start could not be solved (or np.linalg.LinAlgError).
    """
    est = [k for k, n in enumerate(DH_NAMES) if n not in held]
    nominal = tried[0]
    if not isinstance(nominal.outcome, Fit):
        raise nominal.outcome
    first = nominal.outcome.solution
    if len(tried) == 1:
        if found.dh is None:
            return Minima(first, nominal.start, Check(NAME, True, "no other start: the DH search found none "
                                                                   f"({found.reason})"))
        return Minima(first, nominal.start, Check(
            NAME, True, f"the search's proposal and its {found.n_agreeing} agreeing starts lie within {AGREE_SIGMA:g} "
            "sigma of the minimum from the rig file's DH on every estimated parameter"))
    ends = [(t.start, t.outcome.solution) for t in tried[1:]
            if isinstance(t.outcome, Fit) and t.outcome.solution.converged]  # a start lost or not converged: none
    named = [(nominal.start, first), *ends]
    lost = len(tried) - len(named)
    scale = math.sqrt(max(1.0, first.reduced_chi2))
    costs = [cost(s, scale) for _, s in named]
    k = int(np.argmin(costs))  # the lowest, where it is another minimum that fits clearly better than the first's
    if k and (costs[0] - costs[k] < LR_LIMIT or not _apart(named[k][1], first, est)):
        k = 0
    best_start, best = named[k]
    others = [(at.name, s, c - costs[k]) for i, ((at, s), c) in enumerate(zip(named, costs, strict=True)) if i != k]
    n_other = len(tried) - 1 - lost
    what = (f"{n_other} other start{'s' if n_other != 1 else ''} (the DH search's proposal and agreeing starts, "
            f"{found.n_agreeing} of {found.n_starts})" + (f"; {lost} lost the scene's planes" if lost else ""))
    return Minima(best, best_start, _judged(best, others, est, what))


def _apart(sol: Solution, ref: Solution, est: list[int]) -> bool:
    """Whether ``sol`` lies more than AGREE_SIGMA of ``ref``'s 1-sigma from it on an estimated DH parameter."""
    z = np.abs(dh_difference(sol.params.dh.vector(), ref.params.dh.vector())) / np.maximum(ref.dh_sigma, 1e-300)
    return bool(np.any(z[est] > AGREE_SIGMA))


def _start_name(i: int) -> str:
    return "the DH search's proposal" if i == 0 else f"the DH search's agreeing start {i}"


def _judged(best: Solution, others: list[tuple[str, Solution, float]], est: list[int], what: str) -> Check:
    """The check "starts agree": every other minimum the same as ``best`` (within AGREE_SIGMA) or worse by the
    likelihood-ratio rule (lrfcal.estimate.checks.judge_minima); ``others``: (start, minimum, cost above best's)."""
    sigma = best.dh_sigma
    far = np.zeros(4)
    verdicts: list[tuple[str, float, list[str]]] = []
    for name, sol, extra in others:
        z = np.abs(dh_difference(sol.params.dh.vector(), best.params.dh.vector())) / np.where(sigma > 0, sigma, np.inf)
        z = np.where(np.isin(np.arange(4), est), z, 0.0)
        far = np.maximum(far, z)
        apart = [DH_NAMES[k] for k in est if z[k] > AGREE_SIGMA]
        if apart:
            verdicts.append((name, extra, apart))
    worst = ", ".join(f"{DH_NAMES[k]} {far[k]:.1f} sigma" for k in est)
    if not verdicts:
        return Check(NAME, True, f"{what} converge to the estimate within {AGREE_SIGMA:g} sigma ({worst})")
    lr = min(v[1] for v in verdicts)
    ok, words = judge_minima(lr)
    if ok:
        return Check(NAME, True, f"{what}: the other minima fit the scene's planes worse ({words}); the estimate is "
                                 f"the lowest ({worst})")
    apart = sorted({n for v in verdicts if v[1] <= LR_LIMIT for n in v[2]}, key=DH_NAMES.index)
    return Check(NAME, False, f"{what} end in another minimum that fits the scene's planes as well ({words}), "
                              f"{', '.join(apart)} apart (farthest {worst}): the scene's planes do not determine "
                              f"{', '.join(apart)}; calibrate in a scene with more planes across the motor axis, or "
                              "with markers")


def _other_starts(candidates: list[DH], nominal: DH, first: Solution, est: list[int]) -> list[DH]:
    """The starts to run: each candidate as the twin nearest the nominal, its held parameters at the nominal's
    values, without those within AGREE_SIGMA of the nominal's minimum ``first`` or of a start kept before on every
    estimated parameter (the first, the proposal, kept first; then the farthest from it), at most
    MAX_OTHER_STARTS."""
    sigma = first.dh_sigma
    ref = nominal.vector()
    out: list[tuple[float, DH]] = []
    for i, cand in enumerate(candidates):
        near = min((cand, *(t for _, t, _ in dh_twins(cand))),
                   key=lambda t: float(np.sum(np.abs(dh_difference(t.vector(), ref)) / TWIN_SCALE)))
        v = np.where(np.isin(np.arange(4), est), near.vector(), ref)
        z = np.abs(dh_difference(v, first.params.dh.vector()))[est] / np.maximum(sigma[est], 1e-12)
        if z.size and z.max() > AGREE_SIGMA:
            out.append((math.inf if i == 0 else float(z.max()), DH(*(float(x) for x in v))))
    out.sort(key=lambda p: -p[0])
    kept: list[DH] = []
    for _, dh in out:  # a start within AGREE_SIGMA of one kept tests nothing more
        if all(np.max(np.abs(dh_difference(dh.vector(), k.vector()))[est] / np.maximum(sigma[est], 1e-12))
               > AGREE_SIGMA for k in kept):
            kept.append(dh)
    return kept[:MAX_OTHER_STARTS]


__all__ = ["AGREE_SIGMA", "MAX_OTHER_STARTS", "NOMINAL", "Cost", "Minima", "PlaneSets", "PlaneStart", "further",
           "lowest", "searched"]
