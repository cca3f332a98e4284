"""Targetless calibration: the DH parameters from the flatness of the scene's own planes (no markers, no tape).

1. timing: the joint states and the scans they cover          4. the targetless cost minimised from every start
2. planes: segmented ONCE, in the cloud reprojected at the        (the rig file's DH, the DH search's proposal and its
   rig file's DH (lrfcal.stages.planes), grazing and edge         agreeing starts): every plane return's ray-plane
   returns and the rig's own parts left out: which return lies    range residual, the planes free (and the scanner's
   on which plane is fixed from here on                           range error along the scan, with --range-pattern)
                                                                  (lrfcal.estimate.request.PlaneRequest); the lowest
3. observability: which of a, alpha, b, beta (and the clock       cost is the estimate
   offset) the scene determines, from the information at    5. checks: convergence, observability, reduced
   the start and again at the estimate; the others are            chi-square, a second opinion (even / odd passes),
   held at the nominal value                                      held-out planes, starts agree (another minimum
                                                                  that fits as well: not determined)
                                                               6. reprojection, flatness before / after

The steps run as lrfcal.stages.scene.PlaneWay (lrfcal.pipeline's loop); this module holds the segmentation and the
one cost every start minimises (:class:`OneCost`).

**One cost, which cannot oscillate.** The planes and their returns are segmented once, at the start, and that
assignment is never made again: the estimate minimises one robust point-to-plane cost over it (the planes' normals
and offsets free nuisances, a Huber pass then the returns beyond 4 robust sigma left out, lrfcal.estimate.engine),
whatever start it runs from. There is no round to stop at: a calibration that segmented again at each new estimate
(the version before, "segment-and-solve rounds") swung between two segmentations on real recordings (the URG-04LX
box: beta 1-3 deg between the last two rounds) and its verdict depended on which half of the scans was given. The
starts all minimise the same function, so where they end elsewhere the scene's planes fit two rigs (a property of
the data: the check "starts agree", lrfcal.stages.starts); the lowest cost among them is the estimate. The
segmentation at the start takes the planes :data:`BENDING_M` thicker than the noise, so that a nominal DH a few mm
and degrees off still puts a wall's returns on one plane; returns the start puts on the wrong plane (near edges)
are the robust passes' to leave out.

Without markers there is no world frame: the planes and the cloud are in the motor frame M, and the mount pose is
not estimated. A parameter the scene does not determine (1-sigma beyond lrfcal.estimate.observability.LIMITS, e.g. b and
alpha when every plane contains the motor axis) is held at its nominal value and named, never estimated; the
nominal's uncertainty (CalibConfig.nominal_tolerance: the rig file's dh_tolerance) is then carried into the others'
covariance (a "consider" covariance), so that holding a wrong nominal cannot make the others confidently wrong.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, replace
from typing import Protocol

import numpy as np
from numpy.typing import NDArray

from lrfcal.errors import CalibrationError
from lrfcal.estimate import observability
from lrfcal.estimate.request import PlaneOptions, PlaneRequest
from lrfcal.model.kinematics import DH, Params, Pose, beam_rays_M, points_M_trig
from lrfcal.model.motor import MotorClock
from lrfcal.model.plane import Footing
from lrfcal.model.scanner import jump_edges, true_returns
from lrfcal.model.unknowns import core_vector
from lrfcal.runtime.forked import cores
from lrfcal.stages import planes
from lrfcal.stages.sampling import hash_sample
from lrfcal.stages.timing import scan_angles
from lrfcal.types import JointStates, Scans, SelfBox, Solution, Surface, SurfaceReturns

FloatArray = NDArray[np.float64]
DH_NAMES = observability.DH
#: The stages of a targetless calibration, as reported to ``progress`` and in CalibrationResult.timings_s.
STAGES: tuple[str, ...] = ("timing", "planes", "solve", "checks", "starts", "reprojection", "geometry")
#: returns used to segment the planes (the solve uses up to CalibConfig.plane_returns, labelled from these)
SEGMENT_SAMPLES = 40000


class SegmentConfig(Protocol):
    """The configuration the planes are segmented and their returns judged by: its slice of
    lrfcal.config.CalibConfig (which satisfies it; validated and written whole into calibration.yaml there).
    ``range_sigma_m`` is resolved to a number by lrfcal.pipeline.calibrate before the planes are segmented."""

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
class Segmented:
    """The scene's planes as segmented once, at the start: the plane returns (their plane in ``surface``), every
    sampled return's plane (K,) (-1: none) and the planes; the assignment the targetless cost keeps whatever the
    estimate (module docstring)."""

    returns: SurfaceReturns
    labels: NDArray[np.int64]
    planes: list[planes.ScenePlane]


@dataclass(frozen=True)
class Start:
    """Where the planes are segmented, and how the returns are put on them: the DH, the clock offset [s], the
    planes' thickness [m] (the noise plus what a start's DH bends a plane by), the gate [m] within which a return
    joins its nearest segmented neighbour's plane, and the clearance [m] from every other plane its ray must meet
    its own at; ``footing_here``: the incidence and the clearance judged here (False: left to the estimate, which
    judges them at every estimate, :attr:`footing`)."""

    dh: DH
    tau: float
    thickness_m: float
    gate_m: float
    clearance_m: float
    footing_here: bool = True

    @staticmethod
    def of(dh: DH, tau: float, config: SegmentConfig, bending_m: float = 0.0) -> Start:
        """The targetless cost's start at (dh, tau) (module docstring): planes ``bending_m`` thicker than four sigma
        of the noise, a return on the plane of its nearest segmented neighbour within :data:`GATE` times that (the
        cut is the estimate's, at the estimate: no selection at the start), the incidence and the clearance (four
        sigma: where a beam's footprint straddles two surfaces) judged at every estimate."""
        thickness = 4.0 * _sigma(config) + bending_m
        return Start(dh, tau, thickness, GATE * thickness, 4.0 * _sigma(config), footing_here=False)

    def footing(self, config: SegmentConfig) -> Footing:
        """The rule the estimate judges where a return counts by (lrfcal.model.plane.Footing)."""
        return Footing(math.cos(config.max_incidence_rad), self.clearance_m)

    def segment(self, beams: Beams, seg: NDArray[np.int64], motor: MotorClock, config: SegmentConfig) -> Segmented:
        """:func:`plane_returns_at` here."""
        return Segmented(*plane_returns_at(beams, seg, motor, self.dh, self.tau, self.thickness_m, config,
                                           labelling=self))


#: how far a plane of the scene may bend out of flat at the rig file's DH, beyond the noise, and still be segmented
#: as one [m] (a nominal DH a few mm and a degree or two off bends a wall 2 m away by about this much)
BENDING_M = 0.02
#: a return joins the plane of its nearest segmented neighbour within this many of the planes' thickness at the
#: start (wide: which returns count is the estimate's 4-sigma cut, judged at the estimate; a gate as narrow as the
#: thickness selects the returns by how the start bends the planes, and biased the estimate towards the start by up
#: to 10 sigma on room_box's random truths 2 deg from their nominal)
GATE = 3.0
#: where the estimate judges the incidence, the start leaves out only the returns beyond the incidence limit and
#: this much more (a ray nearly along its plane has no range on it to solve with) [rad]
SLACK_RAD = math.radians(10.0)


def _sigma(config: SegmentConfig) -> float:
    assert config.range_sigma_m is not None, "resolved by lrfcal.pipeline.calibrate"
    return float(config.range_sigma_m)


@dataclass(frozen=True)
class OneCost:
    """The targetless cost every start minimises (module docstring), but for where it starts: the range noise [m],
    the motor clock (None: the clock offset held), the parameters held at the start's values, the design drawing's
    prior on the DH ((4,) mean and sigma), where a return counts (lrfcal.model.plane.Footing) and whether the
    scanner's range error along the scan is a nuisance of it (lrfcal.model.range_pattern)."""

    range_sigma_m: float
    clock: MotorClock | None
    hold: tuple[str, ...]
    prior: tuple[FloatArray, FloatArray]
    footing: Footing
    range_pattern: bool = False

    def request(self, segmented: Segmented, dh: DH, tau: float) -> PlaneRequest:
        """The cost over the planes and returns of ``segmented`` (their assignment fixed), from (dh, tau): what to
        estimate (lrfcal.estimate.request.PlaneRequest).

        Raises:
            CalibrationError: the scene shows no plane.
        """
        if not segmented.planes:
            raise CalibrationError("targetless: the scene shows no plane to solve on")
        return PlaneRequest(segmented.returns, Params(MOTOR_FRAME, dh), self.range_sigma_m, self.clock, tau,
                            self.hold, self.prior, PlaneOptions(footing=self.footing, range_pattern=self.range_pattern))


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


def mixed_pixels(scans: Scans, joints: JointStates, clock_offset_s: float, range_sigma_m: float
                 ) -> NDArray[np.bool_]:
    """The returns (S, N) beside a jump edge, along the scan or across it (lrfcal.model.scanner.jump_edges, the
    scans' motor angles at ``clock_offset_s``): a footprint straddling a near surface's edge and a far one behind it
    reports a range on neither, and a plane's returns must lie on it. On the replica of the real room
    (scenarios/urg_room_90.yaml, the stand and the clutter left out, white noise) the desk top's edge, straddled
    across the scan plane as the stand tilts over it, biased a by -1.7 sigma and b by -1.8 sigma on average (12
    seeds) where these returns were kept; -0.45 and -0.40 sigma without them (docs/real-data.md)."""
    return jump_edges(scans.ranges_m, scans.mu_rad, scan_angles(scans, joints, clock_offset_s), range_sigma_m)


#: how far from a declared part of the rig a beam may pass and still count as seeing it [m]: the nominal DH a few mm
#: and a degree or two off puts the part up to about 1 cm from where its rays pass at the stand's 5-20 cm, and a
#: beam's footprint straddles the part's edge and what lies behind it (docs/real-data.md: chosen on the room
#: replica, not yet on another rig)
SELF_MARGIN_M = 0.02


def own_returns(scans: Scans, joints: JointStates, clock_offset_s: float, dh: DH, boxes: Sequence[SelfBox]
                ) -> NDArray[np.bool_]:
    """The returns (S, N) whose beams meet the rig's own parts the rig file declares (``boxes`` fixed to M, each
    grown by :data:`SELF_MARGIN_M`), the rays cast with the nominal ``dh`` at the scans' motor angles: the stand a
    tilting scanner sees at large tilts is no scene (as ROS's laser_filters LaserScanBoxFilter leaves a robot's body
    out). Judged by the ray alone, not by the range it returned: a rule on the return's measured position keeps,
    at the edge of a part's margin, the returns whose noise reads long and leaves out those that read short, which
    biased the room replica's b by +0.8 sigma on average (docs/real-data.md). On that replica the stand's close
    returns made alpha's sigma about 20 % narrow and left a and b undetermined."""
    out = np.zeros(scans.ranges_m.shape, dtype=bool)
    if not boxes:
        return out
    s, b = np.nonzero(np.isfinite(scans.ranges_m))
    # each scan's angle at its stamp: the motor's turn within a scan (a degree at 10 deg/s) moves a part 20 cm away
    # by 3.5 mm, within the margin
    origin, direction = beam_rays_M(scan_angles(scans, joints, clock_offset_s)[s], scans.mu_rad[s, b], dh)
    meets = np.zeros(s.size, dtype=bool)
    for box in boxes:
        T = box.pose.matrix()
        o, d = (origin - T[:3, 3]) @ T[:3, :3], direction @ T[:3, :3]  # in the box's frame: R^T (p - t), row-wise
        half = 0.5 * np.asarray(box.size_m) + SELF_MARGIN_M
        with np.errstate(divide="ignore", invalid="ignore"):  # a ray parallel to a face: +-inf (NaN on its plane)
            t1, t2 = (-half - o) / d, (half - o) / d
        enter = np.max(np.fmin(t1, t2), axis=1)  # fmin / fmax: a NaN counts as the other bound
        leave = np.min(np.fmax(t1, t2), axis=1)
        meets |= leave >= np.maximum(enter, 0.0)  # the slabs' intervals overlap ahead of the scanner
    out[s[meets], b[meets]] = True
    return out


def plane_returns_at(beams: Beams, seg: NDArray[np.int64], motor: MotorClock, dh: DH, tau: float,
                   thickness_m: float, config: SegmentConfig, intrinsics: Mapping[str, float] | None = None,
                   labelling: Start | None = None
                   ) -> tuple[SurfaceReturns, NDArray[np.int64], list[planes.ScenePlane]]:
    """Segment the planes on the ``seg`` subsample of the cloud at (dh, tau) and ``intrinsics`` (name -> value, the
    scales and offsets of lrfcal.model.unknowns; absent ones at their start); label every sampled return with the
    plane of its nearest segmented neighbour when it lies within ``thickness_m`` of that plane, meets it at
    less than ``config.max_incidence_rad`` (grazing returns read short: the footprint spreads along the plane) and
    its ray meets it ``thickness_m`` from every other plane (edges: mixed pixels); ``labelling`` (a :class:`Start`):
    its gate and clearance instead, and the incidence and clearance only where it judges them here.
    The returns keep what the scanner and the servo reported (the solve applies the model to them)."""
    lam = motor.angle(beams.times_s, tau)
    r_true, lam_true, mu_true = true_returns(core_vector(dh, intrinsics or {}), beams.ranges_m, lam, beams.mu_rad)
    phi = dh.beta + mu_true
    trig = (np.cos(lam_true), np.sin(lam_true), np.cos(phi), np.sin(phi))  # shared by the points and the rays
    P = points_M_trig(r_true, *trig, dh)
    seg_labels, found = planes.segment_planes(P[seg], thickness_m=thickness_m)
    labels = np.full(P.shape[0], -1, dtype=np.int64)
    if labelling is not None and not labelling.footing_here:  # the cost's planes: one per surface (clearance)
        seg_labels, found = _coincident_merged(P[seg], seg_labels, found, thickness_m)
    if found:
        rule = labelling or Start(dh, tau, thickness_m, thickness_m, thickness_m)
        strict = (math.cos(config.max_incidence_rad), rule.clearance_m)
        # where the estimate judges the footing, the start leaves out only the rays nearly along their plane
        loose = strict if rule.footing_here else (math.cos(min(config.max_incidence_rad + SLACK_RAD,
                                                               math.pi / 2 - SLACK_RAD)), 0.0)
        labels, footed = _labelled(P, trig, dh, seg, seg_labels, found, rule.gate_m, loose, strict)
        # a plane needs its returns where the footing holds at the start (else the estimate would find none). One
        # without is no surface the beams see; where its segmented points lie on the planes that are, as their own
        # returns do (on the box replica: the patches where the motor axis meets the two side walls, joined by the
        # segmentation into a plane the beams graze), they are theirs, and every return is labelled again: labelled
        # beside it, the side walls' returns were lost to it or cut by its clearance, and beta came out 4 sigma off
        # on such a seed (docs/method.md). One off the others (a surface seen only at grazing incidence) stays for
        # the labelling, and its returns are left out
        keep = _seen(np.where(footed, labels, -1), len(found))
        merged_labels, merged = _dissolved(P[seg], seg_labels, found, keep, _sigma(config))
        if len(merged) < len(found):  # one was dissolved: labelled again, and judged again
            labels, footed = _labelled(P, trig, dh, seg, merged_labels, merged, rule.gate_m, loose, strict)
            found = merged
            keep = _seen(np.where(footed, labels, -1), len(found))
        labels, found = _renumbered(labels, keep, len(found)), [found[k] for k in keep]
    returns = planes.plane_returns(labels, found, beams.scan, beams.beam, lam, beams.mu_rad, beams.ranges_m,
                                   beams.times_s)
    return returns, labels, found


def _labelled(P: FloatArray, trig: tuple[FloatArray, ...], dh: DH, seg: NDArray[np.int64],
              seg_labels: NDArray[np.int64], found: list[planes.ScenePlane], gate_m: float,
              footing: tuple[float, float], strict: tuple[float, float]) -> tuple[NDArray[np.int64], NDArray[np.bool_]]:
    """Every return's plane (K,) (-1: none) for :func:`plane_returns_at`: its nearest segmented neighbour's (of the
    returns ``seg`` (S,), labelled ``seg_labels`` (S,)) where the return lies within ``gate_m`` of that plane and its
    footing holds (``footing``: its beam meets the plane at a |cos| of at least the first, and the ray's hit on it lies
    farther than the second [m] from every other plane); and whether the ``strict`` footing holds too (K,).
    ``P`` (K, 3) the returns in M at ``dh``, ``trig`` the cos and sin (K,) of their motor
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
    near = np.abs(P[:, 0] * n[0] + P[:, 1] * n[1] + P[:, 2] * n[2] - off_l) <= gate_m
    nd = d[0] * n[0] + d[1] * n[1] + d[2] * n[2]
    keep = near & (np.abs(nd) >= footing[0])
    kept_strict = near & (np.abs(nd) >= strict[0])
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
        own = labels == j
        keep &= (dist[:, j] > footing[1]) | own
        kept_strict &= (dist[:, j] > strict[1]) | own
    return np.where(keep, labels, -1), kept_strict & keep


#: two segmented planes whose normals lie within this angle and whose offsets within the planes' thickness are one
#: surface split by a start that bends it [rad]
MERGE_ANGLE_RAD = math.radians(5.0)


def _coincident_merged(Q: FloatArray, labels: NDArray[np.int64], found: list[planes.ScenePlane], thickness_m: float
                       ) -> tuple[NDArray[np.int64], list[planes.ScenePlane]]:
    """The segmented points ``Q`` (S, 3) and their planes with every pair of coincident planes (normals within
    :data:`MERGE_ANGLE_RAD`, offsets within ``thickness_m``) merged into one, fitted afresh to their points: a surface
    a start bends is segmented in pieces, and two planes where there is one surface would leave the returns near their
    seam clear of neither (lrfcal.model.plane.Footing)."""
    parent = list(range(len(found)))

    def root(i: int) -> int:
        while parent[i] != i:
            i = parent[i]
        return i

    cos_merge = math.cos(MERGE_ANGLE_RAD)
    for i in range(len(found)):
        for j in range(i + 1, len(found)):
            c = float(found[i].normal @ found[j].normal)
            apart_m = abs(found[i].offset_m - math.copysign(1.0, c) * found[j].offset_m)
            if abs(c) >= cos_merge and apart_m <= thickness_m:
                parent[root(j)] = root(i)
    roots = sorted({root(i) for i in range(len(found))})
    if len(roots) == len(found):
        return labels, found
    new_of = np.array([roots.index(root(i)) for i in range(len(found))] + [-1], dtype=np.int64)
    labels = new_of[np.where(labels >= 0, labels, len(found))]
    merged = []
    for k in range(len(roots)):
        pts = Q[labels == k]
        normal, offset, rms = planes.fit_plane(pts)
        if offset < 0:  # pointing away from the origin (lrfcal.stages.planes.ScenePlane)
            normal, offset = -normal, -offset
        merged.append(planes.ScenePlane(normal, offset, int(len(pts)), rms, pts.mean(0)))
    return labels, merged


def _seen(counted: NDArray[np.int64], n_planes: int) -> NDArray[np.int64]:
    """The planes (of ``n_planes``) with at least MIN_PLANE_RETURNS returns labelled theirs in ``counted`` (K,) (-1:
    none): the others are mostly grazed, no surface the beams see."""
    return np.flatnonzero(np.bincount(counted[counted >= 0], minlength=n_planes) >= MIN_PLANE_RETURNS)


def _dissolved(Q: FloatArray, labels: NDArray[np.int64], found: list[planes.ScenePlane], keep: NDArray[np.int64],
               sigma_m: float) -> tuple[NDArray[np.int64], list[planes.ScenePlane]]:
    """The segmented points ``Q`` (S, 3), labelled ``labels`` (S,) with ``found``'s planes, with each plane not in
    ``keep`` dissolved where its points lie on the kept planes as their own returns do (their median distance from
    the nearest kept plane within the range noise ``sigma_m``; a plane's own returns: 0.67 sigma): each point joins
    its nearest kept plane. The kept planes first, in order, then the planes not dissolved, whole."""
    kept = [found[k] for k in keep]
    if len(kept) == len(found):
        return labels, found
    out = _renumbered(labels, keep, len(found))
    whole: list[planes.ScenePlane] = []
    N = np.array([p.normal for p in kept]).reshape(-1, 3)
    off = np.array([p.offset_m for p in kept])
    for k in np.setdiff1d(np.arange(len(found)), keep):
        mine = np.flatnonzero(labels == k)
        dist = np.abs(Q[mine] @ N.T - off)
        if kept and mine.size and np.median(dist.min(1)) <= sigma_m:
            out[mine] = dist.argmin(1)
        else:
            out[mine] = len(kept) + len(whole)
            whole.append(found[k])
    return out, kept + whole


def _renumbered(labels: NDArray[np.int64], keep: NDArray[np.int64], n_planes: int) -> NDArray[np.int64]:
    """``labels`` (K,) of ``n_planes`` planes with only the planes ``keep`` (sorted indices) left, renumbered in
    order; the others' returns -1."""
    remap = np.full(n_planes + 1, -1, dtype=np.int64)
    remap[keep] = np.arange(keep.size)
    return remap[np.where(labels >= 0, labels, n_planes)]


def scene_plane_returns(scans: Scans, joints: JointStates, sol: Solution, skip: NDArray[np.bool_],
                        marker_planes: list[Surface], config: SceneConfig) -> tuple[SurfaceReturns, list[Surface]]:
    """Every plane of the scene other than the markers' own (stage 6b generalised): segmented in the cloud at a
    marker calibration ``sol``, in W, as surfaces without a prior (free planes) and their returns, numbered after
    ``marker_planes``. ``skip`` (S, N): the marker returns, left out."""
    motor = MotorClock.from_joints(joints)
    beams = sample_returns(scans, config.plane_returns, skip)
    seg = hash_sample(beams.scan, beams.beam, SEGMENT_SAMPLES)  # the sample's first, in hash order
    thickness = 4.0 * _sigma(config) * max(1.0, math.sqrt(sol.reduced_chi2))  # at a calibrated estimate
    returns, labels, found = plane_returns_at(beams, seg, motor, sol.params.dh, sol.clock_offset_s, thickness,
                                              config, sol.intrinsic_values)
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


__all__ = ["BENDING_M", "MOTOR_FRAME", "STAGES", "Beams", "SceneConfig", "SegmentConfig", "Segmented", "Start",
           "OneCost", "merge_returns", "plane_returns_at", "sample_returns", "scene_plane_returns"]
