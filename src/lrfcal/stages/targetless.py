"""Targetless calibration: the DH parameters from the flatness of the scene's own planes (no markers, no tape).

1. timing: the joint states and the scans they cover          4. solve: every plane return's ray-plane range
2. planes: segmented from the cloud reprojected with the          residual, planes free
(lrfcal.estimate.solve.solve_planes);
   current DH (lrfcal.stages.planes), grazing returns left out          2.-4. repeated, re-segmenting with the new
   estimate
3. observability: which of a, alpha, b, beta (and the clock    5. checks: the rounds settled, convergence,
   offset) the scene determines, from the information at        observability, reduced chi-square, a second
   the start; the others are held at the nominal value            opinion (even / odd passes), held-out planes
                                                               6. reprojection, flatness before / after

The steps run as lrfcal.stages.scene.PlaneWay (lrfcal.pipeline's orchestrator); this module holds the rounds and the
segmentation they use.

The rounds of 2.-4. before the DH settle segment and solve the segmentation's own sample (SEGMENT_SAMPLES returns)
when it is at most COARSE_FRACTION of the sampled returns; the settled estimate then segments and solves every
sampled return once (the same DH to 0.1 sigma in a third to two fifths less time: benchmarks/bench_targetless.py).
Rounds that do not settle in MAX_ROUNDS end with two rounds on every return: their difference is added to the
covariance (which returns the segmentation keeps is a model error), and beyond SETTLE_LIMIT_SIGMA the result is
refused, since it would depend on the round the loop stopped at (the real URG-04LX box: docs/real-data.md).

Without markers there is no world frame: the planes and the cloud are in the motor frame M, and the mount pose is
not estimated. A parameter the scene does not determine (1-sigma beyond lrfcal.estimate.observability.LIMITS, e.g. b and
alpha when every plane contains the motor axis) is held at its nominal value and named, never estimated; the
nominal's uncertainty (CalibConfig.nominal_tolerance) is then carried into the others' covariance (a "consider"
covariance), so that holding a wrong nominal cannot make the others confidently wrong.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field, replace
from typing import Protocol

import numpy as np
from numpy.typing import NDArray

from lrfcal.errors import CalibrationError
from lrfcal.estimate import observability, solve
from lrfcal.model.kinematics import DH, Params, Pose, points_M_trig
from lrfcal.model.motor import MotorClock
from lrfcal.model.scanner import true_returns
from lrfcal.model.unknowns import core_vector, dh_difference
from lrfcal.result import PlaneFit
from lrfcal.runtime.forked import cores
from lrfcal.stages import planes
from lrfcal.stages.sampling import hash_sample
from lrfcal.types import Check, JointStates, Scans, Solution, Surface, SurfaceReturns

FloatArray = NDArray[np.float64]
DH_NAMES = observability.DH
#: The stages of a targetless calibration, as reported to ``progress`` and in CalibrationResult.timings_s.
STAGES: tuple[str, ...] = ("timing", "planes", "solve", "checks", "starts", "reprojection", "geometry")
#: returns used to segment the planes (the solve uses up to CalibConfig.plane_returns, labelled from these)
SEGMENT_SAMPLES = 40000


class SegmentConfig(Protocol):
    """The configuration the segment-and-solve rounds read: their slice of lrfcal.config.CalibConfig (which
    satisfies it; validated and written whole into calibration.yaml there). ``range_sigma_m`` is resolved to a
    number by lrfcal.pipeline.calibrate before any round runs."""

    @property
    def range_sigma_m(self) -> float | None: ...
    @property
    def max_incidence_rad(self) -> float: ...


class SceneConfig(SegmentConfig, Protocol):
    """The configuration the scene's returns are sampled and segmented by (:func:`scene_plane_returns`)."""

    @property
    def plane_returns(self) -> int: ...


@dataclass(frozen=True)
class Beams:
    """The sampled returns: scan, beam (K,), ranges_m, mu_rad, times_s (K,) (also the DH proposal's,
    lrfcal.stages.propose)."""

    scan: NDArray[np.int64]
    beam: NDArray[np.int64]
    ranges_m: FloatArray
    mu_rad: FloatArray
    times_s: FloatArray

    def subset(self, idx: NDArray[np.int64]) -> Beams:
        return Beams(self.scan[idx], self.beam[idx], self.ranges_m[idx], self.mu_rad[idx], self.times_s[idx])


@dataclass(frozen=True)
class Segmenting:
    """What every segment-and-solve round of one calibration shares: the sampled returns, the segmentation's sample
    ``seg`` (indices into them), the motor clock, the configuration and the solve (lrfcal.estimate.solve.solve_planes
    with
    the calibration's held parameters, prior and clock)."""

    beams: Beams
    seg: NDArray[np.int64]
    motor: MotorClock
    config: SegmentConfig
    solve_at: Callable[..., Solution]


@dataclass(frozen=True)
class Rounds:
    """The rounds' outcome: the last solution, the one before it when the rounds did not settle (else None), the
    rounds run, and the last segmentation (returns, labels (K,), planes); ``coarse``: the last round on the
    segmentation's sample when those rounds settled (the estimate the round on every return was segmented at), else
    None; ``ended_coarse``: the rounds ended there, without the round on every return (``enough`` of
    :func:`settle_rounds`)."""

    solution: Solution
    unsettled: Solution | None
    rounds: int
    segmented: tuple[SurfaceReturns, NDArray[np.int64], list[planes.ScenePlane]]
    coarse: Solution | None = None
    ended_coarse: bool = False


def settle_rounds(sg: Segmenting, start: _Round,
                  first: tuple[SurfaceReturns, NDArray[np.int64], list[planes.ScenePlane]] | None = None,
                  enough: Callable[[Solution], bool] | None = None) -> Rounds:
    """Segment, solve and re-segment with the new estimate from ``start`` until the DH settle (module docstring);
    ``first``: the start's segmentation of every sampled return when already made (else the rounds on the
    segmentation's sample begin with its segmentation of that sample alone: the same labels there).
    ``enough(solution)``: called with every round's solution on the segmentation's sample; when True the rounds end
    there (:attr:`Rounds.ended_coarse`), without the next round or the round on every return.

    Raises:
        CalibrationError: a round's cloud shows no plane."""
    beams, seg, motor, config = sg.beams, sg.seg, sg.motor, sg.config
    coarse = _coarse(beams, seg)
    if first is not None:
        returns, labels, found = first
    else:  # the first round's segmentation where it is solved: the sample's returns' own labels (_on_sample)
        returns, labels, found = start.segment(*(coarse or (beams, seg)), motor, config)
    sol: Solution | None = None
    before_last: Solution | None = None
    settled = False
    rounds = 0
    for rounds in range(1, MAX_ROUNDS + 1):  # segment, solve, re-segment with the new estimate until the DH settle
        if rounds == 1 and coarse is not None and first is not None:  # the start's segmentation, on its own sample
            returns, labels, found = _on_sample(beams, seg, labels, found, motor, start.tau)
        elif rounds > 1:
            returns, labels, found = start.segment(*(coarse or (beams, seg)), motor, config)
        new = _solve_round(sg.solve_at, returns, found, start, rounds)
        if coarse is not None and enough is not None and enough(new):
            return Rounds(new, None, rounds, (returns, labels, found), new, ended_coarse=True)
        settled = sol is not None and _settled(sol, new)
        before_last, sol, start = sol, new, _Round.after(new, config)
        if settled:
            break
    assert sol is not None
    last_coarse = sol if coarse is not None and settled else None
    # the estimate on every sampled return, segmented at the coarse rounds' estimate; twice when those did not settle
    for _ in range(0 if coarse is None else 1 if settled else 2):
        returns, labels, found = start.segment(beams, seg, motor, config)
        before_last, sol = sol, _solve_round(sg.solve_at, returns, found, start, rounds + 1)
        start, rounds = _Round.after(sol, config), rounds + 1
    return Rounds(sol, None if settled else before_last, rounds, (returns, labels, found), last_coarse)


#: segment-and-solve rounds at most before the DH settle (then the last two on every return are compared)
MAX_ROUNDS = 5
#: the last two rounds on every return may differ by this many sigma at most when the rounds do not settle: more,
#: and the estimate depends on the round it stops at (the planes are not segmented consistently): refused
SETTLE_LIMIT_SIGMA = 1.0

#: the rounds before the DH settle solve the segmentation's own sample (SEGMENT_SAMPLES returns) when it is at most
#: this fraction of the sampled returns; one round on every sampled return follows (module docstring)
COARSE_FRACTION = 0.5


@dataclass(frozen=True)
class _Round:
    """Where a round segments the planes: the DH, the clock offset [s], the planes' thickness [m] and the
    intrinsics (name -> value, lrfcal.model.unknowns; absent ones at their start)."""

    dh: DH
    tau: float
    thickness_m: float
    intrinsics: Mapping[str, float] = field(default_factory=dict)

    @staticmethod
    def after(sol: Solution, config: SegmentConfig) -> _Round:
        """The next round's, from a round's solution: its estimate, the noise it found."""
        assert config.range_sigma_m is not None  # resolved by lrfcal.pipeline.calibrate
        return _Round(sol.params.dh, sol.clock_offset_s,
                      4.0 * config.range_sigma_m * max(1.0, math.sqrt(sol.reduced_chi2)), sol.intrinsic_values)

    def segment(self, beams: Beams, seg: NDArray[np.int64], motor: MotorClock, config: SegmentConfig
                ) -> tuple[SurfaceReturns, NDArray[np.int64], list[planes.ScenePlane]]:
        """:func:`plane_returns_at` here."""
        return plane_returns_at(beams, seg, motor, self.dh, self.tau, self.thickness_m, config, self.intrinsics)


def first_round(dh: DH, tau: float, config: SegmentConfig) -> _Round:
    """The first round of a calibration from (dh, tau): its planes' thickness the noise plus what a nominal DH bends
    a plane by."""
    assert config.range_sigma_m is not None  # resolved by lrfcal.pipeline.calibrate
    return _Round(dh, tau, 4.0 * config.range_sigma_m + 0.02)


def _coarse(beams: Beams, seg: NDArray[np.int64]) -> tuple[Beams, NDArray[np.int64]] | None:
    """The coarse rounds' returns, the segmentation's sample (all of it segmented), or None when it is not much
    smaller than the sampled returns."""
    if seg.size > COARSE_FRACTION * beams.scan.size:
        return None
    return beams.subset(seg), np.arange(seg.size)


def _round_difference(a: Solution, b: Solution) -> FloatArray:
    """b's DH minus a's (4,), angles wrapped; 0 where a parameter is held (no sigma)."""
    d = dh_difference(b.params.vector()[6:], a.params.vector()[6:])
    return np.where(np.isfinite(b.sigma[6:10]), d, 0.0)


def settle_check(before_last: Solution | None, last: Solution, rounds: int) -> Check:
    """Whether the segment-and-solve rounds settled (``before_last`` None), or else the last two rounds on every
    return differ by at most SETTLE_LIMIT_SIGMA of the last one's sigma (statistical, before the difference is added
    to it by :func:`with_round_difference`)."""
    if before_last is None:
        return Check("rounds settled", True, f"the DH moved by less than a tenth of a sigma between two rounds "
                     f"({rounds} rounds)")
    d = _round_difference(before_last, last)
    s = last.sigma[6:10]
    z = np.where(d != 0.0, np.abs(d) / np.where(s > 0, s, np.inf), 0.0)
    k = int(np.argmax(z))
    name = DH_NAMES[k]
    text = f"{math.degrees(d[k]):+.3g} deg" if name in ("alpha", "beta") else f"{d[k] * 1000:+.3g} mm"
    ok = bool(z[k] <= SETTLE_LIMIT_SIGMA)
    detail = (f"the planes' segmentation and the DH did not settle in {rounds} rounds: the last two on every return "
              f"differ by {name} {text} ({z[k]:.1f} sigma), added to the covariance")
    if not ok:
        detail += (f" (limit {SETTLE_LIMIT_SIGMA:g} sigma): the estimate depends on the round it stops at, the scene's "
                   "planes are not segmented the same way twice (small planes, edges, clutter); calibrate in a larger "
                   "scene or with markers")
    return Check("rounds settled", ok, detail)


def with_round_difference(sol: Solution, before_last: Solution | None) -> Solution:
    """``sol`` with the difference d (4,) from the round before it added to its DH covariance (d d^T, a model error:
    which returns the segmentation keeps), when the rounds did not settle (``before_last`` not None)."""
    if before_last is None:
        return sol
    return sol.with_dh_systematic(_round_difference(before_last, sol))


def _solve_round(fit: Callable[..., Solution], returns: SurfaceReturns, found: list[planes.ScenePlane], start: _Round,
                 rounds: int) -> Solution:
    """One round's solve from ``start`` (a Huber pass first in the first round only)."""
    if not found:
        raise CalibrationError(f"targetless: after round {rounds - 1} the cloud shows no plane: the estimate does "
                               "not hold the scene's planes together")
    return fit(returns, Params(MOTOR_FRAME, start.dh), clock_offset_s=start.tau,
               options=solve.PlaneOptions(huber_first=rounds == 1))


#: returns a plane keeps at least (fewer: dropped, mostly grazing returns)
MIN_PLANE_RETURNS = 100

#: returns above which the labelling's nearest-neighbour query runs in a thread per core (scipy's workers)
PARALLEL_QUERY = 50_000

#: the motor frame M as the world frame (without markers there is no other)
MOTOR_FRAME = Pose(0.0, 0.0, 0.0, 0.0, 0.0, 0.0)


def sample_returns(scans: Scans, n: int, skip: NDArray[np.bool_] | None = None) -> Beams:
    """An even subsample (hash of scan and beam) of at most n finite returns (not those where ``skip`` (S, N))."""
    ok = np.isfinite(scans.ranges_m) & (scans.ranges_m > 0)
    scan, beam = np.nonzero(ok if skip is None else ok & ~skip)
    pick = hash_sample(scan, beam, n)
    scan, beam = scan[pick], beam[pick]
    mu = np.asarray(scans.mu_rad)
    return Beams(scan, beam, scans.ranges_m[scan, beam], mu[scan, beam] if mu.ndim == 2 else mu[beam],
                  scans.angle_times_at(scan, beam))


def plane_returns_at(beams: Beams, seg: NDArray[np.int64], motor: MotorClock, dh: DH, tau: float,
                   thickness_m: float, config: SegmentConfig, intrinsics: Mapping[str, float] | None = None
                   ) -> tuple[SurfaceReturns, NDArray[np.int64], list[planes.ScenePlane]]:
    """Segment the planes on the ``seg`` subsample of the cloud at (dh, tau) and ``intrinsics`` (name -> value, the
    scales and offsets of lrfcal.model.unknowns; absent ones at their start); label every sampled return with the
    plane of its nearest segmented neighbour when it lies within ``thickness_m`` of that plane and meets it at
    less than ``config.max_incidence_rad`` (grazing returns read short: the footprint spreads along the plane).
    The returns keep what the scanner and the servo reported (the solve applies the model to them)."""
    lam = motor.angle(beams.times_s, tau)
    r_true, lam_true, mu_true = true_returns(core_vector(dh, intrinsics or {}), beams.ranges_m, lam, beams.mu_rad)
    phi = dh.beta + mu_true
    trig = (np.cos(lam_true), np.sin(lam_true), np.cos(phi), np.sin(phi))  # shared by the points and the rays
    P = points_M_trig(r_true, *trig, dh)
    seg_labels, found = planes.segment_planes(P[seg], thickness_m=thickness_m)
    labels = np.full(P.shape[0], -1, dtype=np.int64)
    if found:
        labels, found = _with_enough_returns(_labelled(P, trig, dh, seg, seg_labels, found, thickness_m,
                                                       math.cos(config.max_incidence_rad)), found)
    returns = planes.plane_returns(labels, found, beams.scan, beams.beam, lam, beams.mu_rad, beams.ranges_m,
                                   beams.times_s)
    return returns, labels, found


def _labelled(P: FloatArray, trig: tuple[FloatArray, ...], dh: DH, seg: NDArray[np.int64],
              seg_labels: NDArray[np.int64], found: list[planes.ScenePlane], thickness_m: float, min_cos: float
              ) -> NDArray[np.int64]:
    """Every return's plane (K,) (-1: none) for :func:`plane_returns_at`: its nearest segmented neighbour's (of the
    returns ``seg`` (S,), labelled ``seg_labels`` (S,)) where the return lies within ``thickness_m`` of that plane, its
    beam meets it at a cosine of at least ``min_cos``, and the ray's hit on it lies farther than ``thickness_m``
    from every other plane. ``P`` (K, 3) the returns in M at ``dh``, ``trig`` the cos and sin (K,) of their motor
    angles and of beta plus their bearings. The beams' origins and directions are those of
    lrfcal.model.kinematics.beam_rays_M, written by component (the same numbers, without (K, 3) temporaries)."""
    has = seg_labels >= 0
    # the nearest segmented neighbour of every return (a segmented return's is itself): exact whatever the threads,
    # on the cores for a big cloud
    labels = seg_labels[has][planes.nearest_of_subset(P, seg[has], cores() if len(P) > PARALLEL_QUERY else 1)]
    N = np.array([p.normal for p in found])
    off = np.array([p.offset_m for p in found])
    cl, sl, cp, sp = trig
    ca, sa = np.cos(dh.alpha), np.sin(dh.alpha)
    ox, oy, oz = dh.a, -dh.b * sa, dh.b * ca
    dy0 = sp * ca
    o = (cl * ox - sl * oy, sl * ox + cl * oy)  # the origin's z is oz
    d = (cl * cp - sl * dy0, sl * cp + cl * dy0, sp * sa)
    n = (N[:, 0][labels], N[:, 1][labels], N[:, 2][labels])
    off_l = off[labels]
    near = np.abs(P[:, 0] * n[0] + P[:, 1] * n[1] + P[:, 2] * n[2] - off_l) <= thickness_m
    nd = d[0] * n[0] + d[1] * n[1] + d[2] * n[2]
    keep = near & (np.abs(nd) >= min_cos)
    # returns near an edge or a corner, where a beam's footprint straddles two surfaces (mixed pixels), are left
    # out: judged by where the RAY meets its plane, not by the measured point, whose range noise would keep
    # the returns that read short on one side of a corner and those that read long on the other (a bias)
    t = (off_l - (o[0] * n[0] + o[1] * n[1] + oz * n[2])) / np.where(np.abs(nd) > 1e-9, nd, 1e-9)
    hit = np.empty_like(P)
    hit[:, 0], hit[:, 1], hit[:, 2] = o[0] + t * d[0], o[1] + t * d[1], oz + t * d[2]
    dist = hit @ N.T  # (K, planes)
    dist -= off
    np.abs(dist, out=dist)
    for j in range(len(found)):  # clear of every other plane
        keep &= (dist[:, j] > thickness_m) | (labels == j)
    return np.where(keep, labels, -1)


def _with_enough_returns(labels: NDArray[np.int64], found: list[planes.ScenePlane]
                         ) -> tuple[NDArray[np.int64], list[planes.ScenePlane]]:
    """The planes left with at least MIN_PLANE_RETURNS (the others, mostly grazing, dropped) and the labels (K,)
    renumbered."""
    counts = np.bincount(labels[labels >= 0], minlength=len(found))
    keep = np.flatnonzero(counts >= MIN_PLANE_RETURNS)
    remap = np.full(len(found), -1, dtype=np.int64)
    remap[keep] = np.arange(keep.size)
    return np.where(labels >= 0, remap[np.maximum(labels, 0)], -1), [found[k] for k in keep]


def _on_sample(beams: Beams, seg: NDArray[np.int64], labels: NDArray[np.int64], found: list[planes.ScenePlane],
               motor: MotorClock, tau: float) -> tuple[SurfaceReturns, NDArray[np.int64], list[planes.ScenePlane]]:
    """:func:`plane_returns_at` on the segmentation's sample ``seg`` at the estimate whose ``labels`` (K,) on every
    sampled return are given: the same segmentation, the same nearest neighbours and tests per return, so the
    labels are those returns' own, with the planes that keep too few of them dropped."""
    sub = beams.subset(seg)
    labels, found = _with_enough_returns(labels[seg], found)
    lam = motor.angle(sub.times_s, tau)
    return planes.plane_returns(labels, found, sub.scan, sub.beam, lam, sub.mu_rad, sub.ranges_m, sub.times_s), \
        labels, found


def _settled(old: Solution, new: Solution) -> bool:
    """The DH estimate moved by less than a tenth of its sigma between two rounds."""
    d, s = _round_difference(old, new), new.sigma[6:10]
    ok = np.isfinite(s) & (s > 0)
    return bool(np.all(np.abs(d[ok]) <= 0.1 * s[ok]))


def scene_plane_returns(scans: Scans, joints: JointStates, sol: Solution, skip: NDArray[np.bool_],
                        marker_planes: list[Surface], config: SceneConfig) -> tuple[SurfaceReturns, list[Surface]]:
    """Every plane of the scene other than the markers' own (stage 6b generalised): segmented in the cloud at a
    marker calibration ``sol``, in W, as surfaces without a prior (free planes) and their returns, numbered after
    ``marker_planes``. ``skip`` (S, N): the marker returns, left out."""
    motor = MotorClock.from_joints(joints)
    beams = sample_returns(scans, config.plane_returns, skip)
    seg = hash_sample(beams.scan, beams.beam, SEGMENT_SAMPLES)  # the sample's first, in hash order
    returns, labels, found = _Round.after(sol, config).segment(beams, seg, motor, config)
    T = sol.params.mount.matrix()
    R, t = T[:3, :3], T[:3, 3]
    keep, out = [], []
    for k, p in enumerate(found):
        n = R @ p.normal
        d = p.offset_m + float(n @ t)
        if any(abs(float(n @ m.normal)) > math.cos(math.radians(5.0)) and abs(abs(d) - abs(m.offset_m)) < 0.05
               for m in marker_planes):
            continue  # a marker plane, already there with the markers' prior
        t1 = np.cross(n, [1.0, 0.0, 0.0] if abs(n[0]) < 0.9 else [0.0, 1.0, 0.0])
        t1 /= np.linalg.norm(t1)
        out.append(Surface(n, d, np.zeros(0, dtype=np.int64), np.array([t1, np.cross(n, t1)]), R @ p.centroid + t,
                           np.full(2, -np.inf), np.full(2, np.inf), np.full(3, np.inf)))
        keep.append(k)
    m = np.isin(returns.surface, keep)
    sub = returns.subset(m)
    remap = np.full(len(found), -1, dtype=np.int64)
    remap[keep] = len(marker_planes) + np.arange(len(keep))
    surf = remap[sub.surface]
    normals = np.array([s_.normal for s_ in out]).reshape(-1, 3)
    offsets = np.array([s_.offset_m for s_ in out])
    local = surf - len(marker_planes)
    return replace(sub, surface=surf, normals=normals[local], offsets_m=offsets[local]), out


def merge_returns(a: SurfaceReturns | None, b: SurfaceReturns) -> SurfaceReturns:
    """The surface returns of ``a`` followed by those of ``b`` (their surface indices kept)."""
    if a is None or not len(a):
        return b
    return a.joined(b)


__all__ = ["MOTOR_FRAME", "STAGES", "Beams", "PlaneFit", "Rounds", "SceneConfig", "SegmentConfig", "Segmenting",
           "first_round", "settle_check",
           "with_round_difference",
           "merge_returns", "plane_returns_at", "sample_returns", "scene_plane_returns", "settle_rounds"]
