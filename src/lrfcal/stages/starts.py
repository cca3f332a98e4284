"""Targetless: a result is written only where the starts the data allow converge to it (issue 46).

The plane solve is local: where the scene's planes hardly constrain a parameter, the segment-and-solve rounds stop
wherever they started, and the sigma of the result (the curvature at that point) does not show it. The real
URG-04LX box moved alpha 5.9 deg and beta 5.0 deg from inspect's proposal while no plane got more than 0.09 mm
thinner, and claimed 0.34 deg; started from the authors' nominal the same recording was refused.

So the calibration from the rig file's DH (the nominal) is repeated from the other starts the recording allows:
the proposal of the DH search (lrfcal.stages.propose: inspect's proposal, the median of the search's agreeing starts)
and
the agreeing starts themselves, the ones farthest from the result first (at most :data:`MAX_OTHER_STARTS`). Every
start solves the same problem: the same sampled returns and segmentation sample, the same parameters held at the
nominal, the same prior around the nominal and clock; only where the rounds start differs. Each is first brought
to the chain's twin nearest the nominal (lrfcal.model.kinematics.dh_twins: flatness cannot tell them apart). A
start closer to the result than :data:`AGREE_SIGMA` of its sigma on every estimated parameter is not run (it
would test nothing). Each estimated DH parameter of every other start's solution must lie within
:data:`AGREE_SIGMA` of the result's 1-sigma (its reported one: statistical, the rounds' difference and the held
parameters' uncertainty) of the result; otherwise the check "starts agree" fails naming the parameters on which
they disagree, and the run is refused (exit 3).

The other starts reuse the result's sampled returns and segmentation sample, and a start's rounds end as soon as one
on the segmentation's sample lands within :data:`NEAR_SIGMA` of where the result's rounds settled on that sample
(both solves of the same returns: no sampling noise in their difference); its estimate is then the result moved by
that difference (docs/starts.md).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from functools import partial

import numpy as np
from numpy.typing import NDArray

from lrfcal.errors import CalibrationError
from lrfcal.estimate import observability
from lrfcal.model.kinematics import DH, dh_twins
from lrfcal.model.unknowns import dh_difference
from lrfcal.result import CalibrationResult, PlaneEvidence
from lrfcal.runtime.forked import call_forked, cores
from lrfcal.stages import propose, targetless
from lrfcal.types import Check, JointStates, Solution

FloatArray = NDArray[np.float64]
DH_NAMES = observability.DH
#: every other start's estimate must lie within this many of the result's 1-sigma of it, on every estimated DH
#: parameter (the same data and problem: only where the rounds start differs)
AGREE_SIGMA = 1.0
#: the other starts run at most (the proposal first, then the agreeing starts farthest from the result)
MAX_OTHER_STARTS = 2
NAME = "starts agree"
#: the scales [m, rad, m, rad] on which a candidate's twin nearest the nominal is chosen (1 cm ~ 0.1 rad)
TWIN_SCALE = np.array([0.01, 0.1, 0.01, 0.1])


def starts_check(fit: CalibrationResult, evidence: PlaneEvidence, joints: JointStates, tau0: float,
                 rounds: tuple[targetless.Segmenting, Solution | None],
                 proposal: Callable[[], propose.DHProposal] | None = None) -> Check:
    """The check "starts agree" of a targetless result ``fit`` (lrfcal.stages.scene.PlaneWay) of ``fit.recording``
    (the scans the ``joints`` cover), its ``evidence``, its rounds started from the clock offset ``tau0`` [s]: the
    module docstring. ``rounds``: what the result's rounds shared (their sampled returns and segmentation sample, held
    parameters, prior and clock) and their last round on the segmentation's sample when those settled
    (lrfcal.stages.targetless.Rounds.coarse, else None). ``proposal``: the DH search's proposal on those scans and
    joints when it was begun before (lrfcal.stages.propose.proposal_ahead, during the fit), else searched here."""
    sol, nominal = fit.solution, fit.recording.nominal.dh
    held = evidence.plane_fit.held
    est = [k for k, n in enumerate(DH_NAMES) if n not in held]
    sigma = sol.sigma[6:10]
    try:
        found = proposal() if proposal is not None else propose.propose_dh(fit.recording.scans, joints)
    except (CalibrationError, np.linalg.LinAlgError) as err:
        found = propose.DHProposal(None, reason=str(err))
    if found.dh is None:
        return Check(NAME, True, f"no other start: the DH search found none ({found.reason})")
    starts = _other_starts([found.dh, *found.agreeing], nominal, sol, est)
    if not starts:
        return Check(NAME, True, f"the search's proposal and its {found.n_agreeing} agreeing starts lie within "
                     f"{AGREE_SIGMA:g} sigma of the result on every estimated parameter")
    sg = _rerun(fit, held, rounds)
    n = max(1, min(cores(), len(starts)))  # the starts are independent: on the cores (lrfcal.runtime.forked)
    done = call_forked({str(g): partial(_solved, sg, tau0, starts[g::n]) for g in range(n)})
    ends = [v for g in range(n) for v in done[str(g)]]
    far = np.zeros(4)
    for v in ends:
        if v is not None:
            d = np.abs(dh_difference(v, sol.params.vector()[6:]))
            far = np.maximum(far, np.where(np.isin(np.arange(4), est), d / np.where(sigma > 0, sigma, np.inf), 0.0))
    lost = sum(v is None for v in ends)
    ran = len(starts) - lost
    what = (f"{ran} other start{'s' if ran != 1 else ''} (the DH search's proposal and agreeing starts, "
            f"{found.n_agreeing} of {found.n_starts})" + (f"; {lost} lost the scene's planes" if lost else ""))
    bad = [DH_NAMES[k] for k in est if far[k] > AGREE_SIGMA]
    worst = ", ".join(f"{DH_NAMES[k]} {far[k]:.1f} sigma" for k in est)
    if not bad:
        return Check(NAME, True, f"{what} converge to the result within {AGREE_SIGMA:g} sigma ({worst})")
    return Check(NAME, False, f"{what} converge elsewhere: they disagree on {', '.join(bad)} (farthest {worst}, "
                 f"limit {AGREE_SIGMA:g} sigma): the scene's planes do not determine {', '.join(bad)}, the result "
                 "depends on where the solve starts; calibrate in a scene with more planes across the motor axis, or "
                 "with markers")


#: a start's rounds end as soon as one on the segmentation's sample lands within this many of the result's 1-sigma
#: of where the result's own rounds settled there, on every estimated DH parameter (module docstring)
NEAR_SIGMA = 0.25


@dataclass(frozen=True)
class _Rerun:
    """What every other start's rounds share (``sg``), and where the result's rounds on the segmentation's sample
    settled (``coarse``, DH (4,); None: they did not run on a sample, or did not settle there), the result's DH (4,)
    and 1-sigma (4,) and the estimated parameters (indices)."""

    sg: targetless.Segmenting
    coarse: FloatArray | None
    result: FloatArray
    sigma: FloatArray
    est: list[int]

    def near(self, sol: Solution) -> bool:
        """Whether a start's round on the sample landed within NEAR_SIGMA of where the result's settled there."""
        if self.coarse is None or not self.est:
            return False
        d = np.abs(dh_difference(sol.params.vector()[6:], self.coarse))[self.est]
        return bool(np.all(d <= NEAR_SIGMA * self.sigma[self.est]))


def _solved(run: _Rerun, tau0: float, starts: list[DH]) -> list[FloatArray | None]:
    """The DH (4,) each start's rounds (from the clock offset ``tau0`` [s]) settle at
    (lrfcal.stages.targetless.settle_rounds), None for a start that loses the scene's planes (not a solution to
    compare). A start whose round on the segmentation's sample lands near
    where the result's rounds settled there (:meth:`_Rerun.near`) ends there: its DH is the result moved by the
    difference of the two (its further rounds, segmented at estimates that close to the result's settled one, would
    end closer)."""
    out: list[FloatArray | None] = []
    sg = run.sg
    for dh in starts:
        try:
            rounds = targetless.settle_rounds(sg, targetless.first_round(dh, tau0, sg.config), enough=run.near)
        except (CalibrationError, np.linalg.LinAlgError):
            out.append(None)
            continue
        v = rounds.solution.params.vector()[6:]
        if rounds.ended_coarse and run.coarse is not None:
            v = run.result + dh_difference(v, run.coarse)
        out.append(v)
    return out


def _other_starts(candidates: list[DH], nominal: DH, sol: Solution, est: list[int]) -> list[DH]:
    """The starts to run: each candidate as the twin nearest the nominal, its held parameters at the nominal's
    values, without those within AGREE_SIGMA of the result or of a start kept before on every estimated parameter
    (the first, the proposal, kept first; then the farthest from the result), at most MAX_OTHER_STARTS."""
    sigma = sol.sigma[6:10]
    ref = nominal.vector()
    out: list[tuple[float, DH]] = []
    for i, cand in enumerate(candidates):
        near = min((cand, *(t for _, t, _ in dh_twins(cand))),
                   key=lambda t: float(np.sum(np.abs(dh_difference(t.vector(), ref)) / TWIN_SCALE)))
        v = np.where(np.isin(np.arange(4), est), near.vector(), ref)
        z = np.abs(dh_difference(v, sol.params.vector()[6:]))[est] / np.maximum(sigma[est], 1e-12)
        if z.size and z.max() > AGREE_SIGMA:
            out.append((math.inf if i == 0 else float(z.max()), DH(*(float(x) for x in v))))
    out.sort(key=lambda p: -p[0])
    kept: list[DH] = []
    for _, dh in out:  # a start within AGREE_SIGMA of one kept tests nothing more
        if all(np.max(np.abs(dh_difference(dh.vector(), k.vector()))[est] / np.maximum(sigma[est], 1e-12))
               > AGREE_SIGMA for k in kept):
            kept.append(dh)
    return kept[:MAX_OTHER_STARTS]


def _rerun(fit: CalibrationResult, held: tuple[str, ...], rounds: tuple[targetless.Segmenting, Solution | None]
           ) -> _Rerun:
    """What the other starts' rounds share with ``fit``'s (``rounds``, see :func:`starts_check`): the same sampled
    returns (the held-out scans skipped), segmentation sample, held parameters, prior and clock."""
    sol, (sg, coarse) = fit.solution, rounds
    est = [k for k, n in enumerate(DH_NAMES) if n not in held]
    return _Rerun(sg, None if coarse is None else coarse.params.vector()[6:], sol.params.vector()[6:],
                  sol.sigma[6:10], est)


__all__ = ["AGREE_SIGMA", "MAX_OTHER_STARTS", "starts_check"]
