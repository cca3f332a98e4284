"""A coarse DH proposal from a recording alone (``lrfcal inspect``): the scan plane's attitude to the motor axis
(alpha, beta) and its offsets (a, b) that make the scene's planes planar, with the proposal's own uncertainty.

The search reuses the targetless calibration's machinery (lrfcal.stages.targetless: the returns' subsample, the planes
segmented in the cloud at the current DH with grazing and edge returns left out, the one cost as a
lrfcal.estimate.request.PlaneRequest: every plane return a ray-plane range residual, planes free). It is started
from every combination of
:data:`START_ALPHA_DEG`, :data:`START_BETA_DEG` and :data:`START_B_M` (a = 0), each segmenting the planes on a
subsample of the returns drawn by its own seed (lrfcal.stages.sampling.hash_sample: two starts' subsamples share
about the fraction of the returns each holds), and each start is solved for all
four DH parameters with a weak prior around the start (:data:`PRIOR_SIGMA`: it keeps a and b from running off where
the scene hardly constrains them), on the targetless calibration's one cost: the planes segmented once, at the
start, and that assignment kept while the solve minimises the cost from it. A start that loses its planes, or whose
offsets leave the plausible range (:data:`MAX_OFFSET_M`), is dropped.

Flatness cannot tell a cloud from its mirror image or from itself turned, so each candidate is first brought to
one representative of the DH that give the same cloud up to a rigid motion and a mirror (:func:`canonical`):

- (a, -alpha, -b, beta) is the cloud mirrored in the motor frame's xy plane, so alpha is proposed in [0, 180] deg;
- (-a, alpha, -b, beta + 180 deg) is the same cloud mirrored and turned, so b is proposed >= 0;
- a negated motor angle (``servo.sign: -1``) with alpha - 180 deg gives the same cloud turned about x_M: the sign of
  the motor angle is therefore not a separate unknown for the planes; the proposal keeps the servo's declared sign.

The candidates are then grouped by attitude (alpha within :data:`AGREE_ALPHA_DEG`, beta within
:data:`AGREE_BETA_DEG`, modulo the 180 deg of the second equivalence); the largest group must hold at least
:data:`MIN_AGREEING` candidates and half of those that converged, else the scene does not determine a proposal
(too few planes, or ambiguous). The proposal is the group's median; each value's 1-sigma is the larger of the
group's spread (1.4826 x the median absolute deviation: over the starts and their subsamples)
and the median of the solves' own 1-sigma (scaled by the square root of their reduced chi-square). A value whose
1-sigma exceeds :data:`DETERMINED` is named as not determined by the scene (its value is the search's best guess,
not a measurement).

This module says what each start estimates (:func:`start_request`), what its minimum proposes (:func:`candidate`)
and the proposal from the candidates (:func:`proposal_of`); it solves nothing. The starts are independent:
lrfcal.pipeline.search solves them on the machine's cores (or ahead, while a targetless calibration goes on) and
collects them in start order, so the proposal does not depend on how many cores there are, nor on which core solved
which start.

Array shapes: K returns.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from lrfcal.config import DEFAULT_MAX_INCIDENCE_RAD
from lrfcal.estimate.request import PlaneRequest
from lrfcal.model.kinematics import DH, dh_twins
from lrfcal.model.motor import MotorClock
from lrfcal.model.unknowns import wrap_pi
from lrfcal.runtime.forked import cores
from lrfcal.stages import targetless
from lrfcal.stages.sampling import hash_sample
from lrfcal.types import JointStates, Scans, Solution

FloatArray = NDArray[np.float64]
#: a start's candidate: its canonical DH and their 1-sigma (4,)
Candidate = tuple[DH, FloatArray]
NAMES = ("a", "alpha", "b", "beta")
#: the starts of the search: every combination (a = 0)
START_ALPHA_DEG = (45.0, 90.0, 135.0)
START_BETA_DEG = (-90.0, 0.0)  # beta + 180 deg with (a, b) negated is the same cloud mirrored (module docstring)
START_B_M = (0.0, 0.1)
#: the weak prior around each start (a, alpha, b, beta) [m, rad]
PRIOR_SIGMA = (0.05, math.radians(30.0), 0.10, math.radians(30.0))
#: the planes' half-width at a start [m] (a coarse start bends the scene's planes by centimetres)
#: the starts are solved in at most this many groups at once, one per core (the first in this process)
MAX_GROUPS = 4
START_THICKNESS_M = 0.04
#: returns sampled for the solves, and the subsample each start segments its planes on
FIT_RETURNS = 12000
SEGMENT_RETURNS = 8000
#: range noise assumed by the solves [m] (the solves' chi-square scales their sigma)
RANGE_SIGMA_M = 0.01
#: a candidate whose |a| or |b| goes beyond this ran off [m]
MAX_OFFSET_M = 0.3


@dataclass(frozen=True)
class _SearchSegmenting:
    """The search's own segmentation settings (lrfcal.stages.targetless.SegmentConfig), fixed whatever a calibration's
    options: the calibration's default incidence limit, the noise the solves assume."""

    range_sigma_m: float = RANGE_SIGMA_M
    max_incidence_rad: float = DEFAULT_MAX_INCIDENCE_RAD

#: the least motor turn a proposal needs [rad]
MIN_TURN_RAD = math.radians(10.0)
#: candidates agree on the attitude within these [deg]; the fewest agreeing candidates for a proposal
AGREE_ALPHA_DEG = 15.0
AGREE_BETA_DEG = 20.0
MIN_AGREEING = 3
#: a group smaller than this gives each value's spread as the larger of the MAD's and the standard deviation
SMALL_GROUP = 5
#: a proposed value whose 1-sigma exceeds this is not determined by the scene [m, rad]
DETERMINED = {"a": 0.05, "alpha": math.radians(10.0), "b": 0.05, "beta": math.radians(15.0)}


@dataclass(frozen=True)
class DHProposal:
    """The search's outcome: ``dh`` the proposal (None: the scene does not determine one, ``reason`` says why),
    ``sigma`` each value's 1-sigma [m, rad], the candidates that converged and those agreeing with the proposal,
    and the search's run time [s]."""

    dh: DH | None
    sigma: dict[str, float] = field(default_factory=dict)
    n_converged: int = 0
    n_agreeing: int = 0
    n_starts: int = 0
    reason: str = ""
    seconds: float = 0.0
    #: the agreeing candidates themselves (canonical), in start order: starts for lrfcal.stages.starts
    agreeing: tuple[DH, ...] = ()

    @property
    def undetermined(self) -> tuple[str, ...]:
        """The proposed values whose 1-sigma exceeds :data:`DETERMINED`."""
        return tuple(n for n in NAMES if not self.sigma.get(n, math.inf) <= DETERMINED[n])

    def comment(self) -> str:
        """One comment line for the rig file: what the values are and each one's uncertainty (or why there is no
        proposal)."""
        if self.dh is None:
            return f"# dh: not proposed: {self.reason}; fill in from the drawings (m, rad; docs/formats.md)"
        s = self.sigma
        parts = [f"a +-{s['a'] * 1000:.1f} mm", f"alpha +-{math.degrees(s['alpha']):.2f} deg",
                 f"b +-{s['b'] * 1000:.1f} mm", f"beta +-{math.degrees(s['beta']):.2f} deg"]
        undet = self.undetermined
        tail = f"; not determined by the scene: {', '.join(undet)}" if undet else ""
        return (f"# dh: proposed from the scene's planes, not measured ({self.n_agreeing} of {self.n_starts} search "
                f"starts agree; 1-sigma {', '.join(parts)}{tail}; the same planes: -alpha with -b, or -a, -b with "
                "beta + 180 deg); check against the drawings")

    def values(self) -> dict[str, float] | None:
        """The proposal as the rig file's dh (m, rad; rounded to 0.1 mm and 0.001 rad), None without one."""
        if self.dh is None:
            return None
        d = self.dh
        return {"a": round(d.a, 4), "alpha": round(d.alpha, 4), "b": round(d.b, 4), "beta": round(d.beta, 4)}


#: the DH search's proposal, when asked for (lrfcal.pipeline.search: begun ahead, solved meanwhile)
Proposal = Callable[[], DHProposal]


def canonical(dh: DH) -> DH:
    """The representative of the DH parameters that give the same cloud up to a rigid motion and a mirror (the
    chain's twins, lrfcal.model.kinematics.dh_twins): alpha in [0, pi], b >= 0, beta in (-pi, pi]."""
    wrapped = DH(a=dh.a, alpha=float(wrap_pi(dh.alpha)), b=dh.b, beta=float(wrap_pi(dh.beta)))
    for d in (wrapped, *(twin for _, twin, _ in dh_twins(wrapped))):
        if 0.0 <= d.alpha <= math.pi and d.b >= 0.0:
            return DH(a=d.a, alpha=d.alpha, b=d.b, beta=float(wrap_pi(d.beta)))
    raise AssertionError("one of the four twins has alpha in [0, pi] and b >= 0")


def motor_turn_rad(joints: JointStates) -> float:
    """How far the motor turns over the recording [rad] (the range of its angle)."""
    p = np.asarray(joints.positions_rad, dtype=float)
    p = p[np.isfinite(p)]
    return float(p.max() - p.min()) if p.size else 0.0


@dataclass(frozen=True)
class Search:
    """What every start of the search reads: the starts, the returns sampled, the motor clock, the configuration,
    and the groups the starts are solved in (one per core, at most MAX_GROUPS)."""

    starts: list[DH]
    beams: targetless.Beams
    motor: MotorClock
    config: targetless.SegmentConfig
    n_groups: int


def search_of(scans: Scans, joints: JointStates, t0: float) -> Search | DHProposal:
    """The search's inputs, or the proposal refused at once (the motor turns too little)."""
    turn = motor_turn_rad(joints)
    starts = [DH(a=0.0, alpha=math.radians(al), b=b, beta=math.radians(be))
              for al in START_ALPHA_DEG for be in START_BETA_DEG for b in START_B_M]
    if turn < MIN_TURN_RAD:
        return DHProposal(None, reason=f"the motor turns only {math.degrees(turn):.1f} deg (a proposal needs "
                          f"{math.degrees(MIN_TURN_RAD):g}): the cloud is nearly one scan plane, whose flatness says "
                          "nothing about the DH", n_starts=len(starts), seconds=time.perf_counter() - t0)
    # the calibration's own sample: without the returns beside a jump edge (mixed pixels, on neither surface)
    mixed = targetless.mixed_pixels(scans, joints, 0.0, RANGE_SIGMA_M)
    return Search(starts, targetless.sample_returns(scans, FIT_RETURNS, skip=mixed), MotorClock.from_joints(joints),
                   _SearchSegmenting(), max(1, min(cores(), MAX_GROUPS, len(starts))))


def start_request(search: Search, k: int) -> PlaneRequest | None:
    """What start ``k`` of the search estimates: the targetless cost (lrfcal.stages.targetless: the planes segmented
    once, at the start, :data:`START_THICKNESS_M` thick, on the start's own subsample, the assignment fixed) from it,
    with the weak prior around it; None when the planes are too few."""
    start = search.starts[k]
    seg = hash_sample(search.beams.scan, search.beams.beam, SEGMENT_RETURNS, seed=100 + k)
    at = targetless.Start.of(start, 0.0, search.config, START_THICKNESS_M - 4.0 * RANGE_SIGMA_M)
    segmented = at.segment(search.beams, seg, search.motor, search.config)
    if len(segmented.planes) < 2 or len(segmented.returns) < 300:
        return None
    prior = (start.vector(), np.array(PRIOR_SIGMA))
    return targetless.OneCost(RANGE_SIGMA_M, None, (), prior, at.footing(search.config)).request(segmented, start, 0.0)


def candidate(sol: Solution) -> Candidate | None:
    """A start's minimum as a candidate: the canonical DH and its 1-sigma (4,) scaled by sqrt(reduced chi-square), or
    None when the solve did not converge or the offsets ran off (:data:`MAX_OFFSET_M`)."""
    dh = sol.params.dh
    sigma = np.asarray(sol.dh_sigma, dtype=float) * math.sqrt(max(1.0, sol.reduced_chi2))
    if not sol.converged or max(abs(dh.a), abs(dh.b)) > MAX_OFFSET_M or not np.all(np.isfinite(sigma)):
        return None
    return canonical(dh), sigma


def proposal_of(search: Search, parts: list[list[tuple[int, Candidate | None]]], t0: float,
                progress: Callable[[int, int], None] | None) -> DHProposal:
    """The proposal from the groups' candidates, collected in start order."""
    n_starts = len(search.starts)
    solved = sorted(kc for part in parts for kc in part)
    if progress is not None:
        progress(n_starts, n_starts)
    found = [cand for _, cand in solved if cand is not None]
    out = _consensus(found, n_starts)
    return DHProposal(out.dh, out.sigma, out.n_converged, out.n_agreeing, n_starts, out.reason,
                      time.perf_counter() - t0, out.group)


@dataclass(frozen=True)
class _Consensus:
    dh: DH | None
    sigma: dict[str, float]
    n_converged: int
    n_agreeing: int
    reason: str
    group: tuple[DH, ...] = ()


def _aligned(ref: DH, dh: DH) -> FloatArray:
    """``dh`` as (a, alpha, b, beta), turned to the representative nearest ``ref`` in beta ((-a, -b, beta + pi) is
    the same cloud), beta unwrapped about ref's."""
    a, b, beta = dh.a, dh.b, dh.beta
    if abs(float(wrap_pi(beta - ref.beta))) > math.pi / 2:
        a, b, beta = -a, -b, beta + math.pi
    return np.array([a, dh.alpha, b, ref.beta + float(wrap_pi(beta - ref.beta))])


def _consensus(found: list[tuple[DH, FloatArray]], n_starts: int) -> _Consensus:
    """The largest group of candidates agreeing on the attitude, its median and spread (module docstring)."""
    n = len(found)
    if n < MIN_AGREEING:
        return _Consensus(None, {}, n, 0, f"only {n} of {n_starts} search starts kept their planes (need "
                          f"{MIN_AGREEING}): the scene shows too few planes")
    al = np.array([d.alpha for d, _ in found])
    be = np.array([d.beta for d, _ in found])
    d_al = np.abs(al[:, None] - al[None, :])
    d_be = np.abs(wrap_pi(2.0 * (be[:, None] - be[None, :]))) / 2.0  # beta modulo 180 deg
    agree = (d_al <= math.radians(AGREE_ALPHA_DEG)) & (d_be <= math.radians(AGREE_BETA_DEG))
    size = agree.sum(1)
    best = int(np.argmax(size + 1e-3 * -np.median(np.abs(d_al), axis=1)))  # ties: the most central
    group = np.flatnonzero(agree[best])
    if group.size < MIN_AGREEING or 2 * group.size < n:
        alphas = ", ".join(f"{math.degrees(a):.0f}" for a in sorted(al))
        return _Consensus(None, {}, n, int(group.size), f"ambiguous: the {n} converged search starts do not agree on "
                          f"the scan plane's attitude (alpha {alphas} deg; the largest group {group.size})")
    X = np.array([_aligned(found[best][0], found[i][0]) for i in group])
    med = np.median(X, axis=0)
    spread = 1.4826 * np.median(np.abs(X - med), axis=0)
    if group.size < SMALL_GROUP:  # the MAD of a few values can hide one far off: their standard deviation too
        spread = np.maximum(spread, np.std(X, axis=0, ddof=1))
    own = np.median(np.array([found[i][1] for i in group]), axis=0)
    sigma = np.maximum(spread, own)
    dh = canonical(DH(a=float(med[0]), alpha=float(med[1]), b=float(med[2]), beta=float(med[3])))
    return _Consensus(dh, dict(zip(NAMES, (float(s) for s in sigma), strict=True)), n, int(group.size), "",
                      tuple(found[i][0] for i in group))


__all__ = ["DETERMINED", "Candidate", "DHProposal", "Proposal", "Search", "canonical", "candidate", "motor_turn_rad",
           "proposal_of", "search_of", "start_request"]
