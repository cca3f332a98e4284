"""The marker observation model: a return on a retroreflective sphere of radius R_m centred at c (in W).

Two models (o, d: the beam's origin and unit direction in W, lrfcal.model.rays; r: the reported range, compared
with what the scanner reports of the predicted true range, rep(r_hat) = range_scale r_hat + range_offset +
marker_range_bias + incidence_bias theta, lrfcal.model.scanner):

* ``"paper"`` (seed paper eq. (10)): residual (o + r_true d - c) / sigma_r, 3 per return (r_true the reported
  range's true range).
* ``"sphere"`` (every return on a marker, sub-beam): v = c - o, t = v.d, e = v - t d (|e| = distance of the
  centre from the ray), u = |e| / R_m,
      r_hat = t - R_m s(u),   s(u) = sqrt(eta softplus((1 - u^2) / eta))   (eta = 0.05, lrfcal.model.sphere)
  s(u) ~ sqrt(1 - u^2) (the depth of the sphere's surface below the centre plane) for u < ~0.97, and is
  smooth with bounded slope near and beyond the rim (s -> 0: a grazing or mixed-pixel return reports the
  rim). Residuals: (r - rep(r_hat)) / sigma_r per return, and the lateral offset e / sigma_lat, sigma_lat = R_m / 2
  (a return's offset spreads over the visible disc: E|e|^2 = R_m^2 / 2), of which the calibration keeps the means
  that locate the centre (lrfcal.model.coverage.centred): its part across the scan plane as one mean per crossing
  of the sweep, its part along the scan line as one mean per line (the spread of the offsets is the disc's width,
  covered by the beams and the sweep: taken as noise, it pulled the motor's angle scale 6 sigma on a board the motor
  axis points at). The robust pass judges each return by its own offset (MarkerSet.chi).
  With a finite beam (divergence delta > 0) the footprint at the marker is a disc of radius k R_m,
  k = r delta / (2 R_m) from the measured range r, and a retroreflector outshines whatever else it covers: s(u)
  becomes S(u, k), the mean of s over the part of the footprint that hits the sphere (footprint_depth), and
  sigma_lat = R_m sqrt(1 + k^2) / 2 (the beam's axis is the point hit on the marker's disc minus its offset within
  the footprint, two independent uniform discs). Modelling the beam as its axis alone leaves the footprint in the
  marker returns' ranges: on lrfsim's 4.4 mrad beam and 5 mm spheres a marker-return range bias of -0.9 mm
  (plane_30deg), +0.04 mm with the footprint (docs/study.md).
  The incidence theta where the beam meets the sphere is atan2(u, s(u)) (sin theta = u on the sphere), its mean over
  the same part of the footprint (footprint_incidence): 0 through the centre, pi/2 at the rim.

Jacobian (chain rule from lrfcal.model.rays' o_j, d_j):
    paper: (o + r_true d)_j / sigma_r, plus d dr_true/dtheta_j / sigma_r for the range's unknowns.
    sphere: v_j = -o_j; t_j = v_j.d + v.d_j; e_j = v_j - t_j d - t d_j; |e|_j = (e/|e|).e_j;
      r_hat_j = t_j - s'(u) |e|_j;  range residual_j = -(range_scale r_hat_j + incidence_bias theta'(u) |e|_j / R_m
      + drep/dtheta_j) / sigma_r;
      lateral_j = e_j / sigma_lat, then the same means as the residual's.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from functools import cached_property

import numpy as np
from numpy.typing import ArrayLike, NDArray

from lrfcal.model.coverage import Coverage, crossing_ids, turning
from lrfcal.model.coverage import centred as centred_rows
from lrfcal.model.kinematics import Params, points_M, transform_points
from lrfcal.model.motor import MotorAngles, MotorClock, motor_angles
from lrfcal.model.observations import Blocks, MarkerModel, MarkerSensor, RowContext, robust_kept
from lrfcal.model.rays import beam_rays
from lrfcal.model.scanner import reported_range, true_range
from lrfcal.model.sphere import footprint_depth, footprint_incidence
from lrfcal.model.unknowns import INC, N_CORE, RSCALE

FloatArray = NDArray[np.float64]

MODELS = tuple(m.value for m in list(MarkerModel))

#: the median of chi2_3 / 3, the squared whitened residual per independent component of a return at unit noise
#: (the robust pass's scale of the marker returns)
CHI2_3_MEDIAN = 0.789


def ray_to_centre(o: FloatArray, d: FloatArray, c: FloatArray) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Where marker centres c sit relative to rays (origin o, unit direction d), broadcast over leading axes (..., 3):
    v = c - o, the distance t = v.d along the ray (...,) and the perpendicular offset e = v - t d (..., 3), |e| the
    centre's distance from the ray."""
    v = c - o
    t = (v * d).sum(-1)
    return v, t, v - t[..., None] * d


def footprint_radius_m(range_m: ArrayLike, divergence_rad: float) -> FloatArray:
    """The beam's footprint radius [m] at ``range_m`` for a full divergence ``divergence_rad`` (0 behind it)."""
    return 0.5 * divergence_rad * np.maximum(np.asarray(range_m, dtype=float), 0.0)


@dataclass(frozen=True)
class MarkerSet:
    """K returns on markers (an observation set, lrfcal.model.observations.ObservationSet): their motor angles (at
    the start clock offset), bearings, ranges, marker centres in W, the sensor (the model variant, the marker radius
    R_m, the beam's full divergence), laser-clock beam times, each return's marker (its index in the marker map, for
    the map's own uncertainty) and scan."""

    lam: FloatArray  # (K,)
    mu: FloatArray  # (K,)
    r: FloatArray  # (K,)
    c: FloatArray  # (K, 3)
    sensor: MarkerSensor
    times: FloatArray | None = None  # (K,)
    marker: NDArray[np.int64] | None = None  # (K,)
    #: (K,) whether the return's lateral residual is used (None: all); see :func:`two_sided`
    lateral: NDArray[np.bool_] | None = None
    #: (K, 3) the scan plane's unit normal (in W) where the lateral residual keeps only its part in the scan plane,
    #: 0 where it keeps all of it (None: all of it everywhere); see :func:`crossings`
    across: FloatArray | None = None
    #: the model variant whose lateral residual keeps only its in-plane part in crossings that turn on their marker
    #: (:func:`crossings`; lrfcal.stages.markers widens the covariance by the DH difference it makes)
    in_plane_at_turns: bool = False
    scan: NDArray[np.int64] | None = None  # (K,) each return's scan (the covariance's clusters without times)
    beam: NDArray[np.int64] | None = None  # (K,) each return's beam in its scan (the range noise's neighbours)
    #: (K, 2, 3) the scan plane's unit normal and the unit direction in it across each ray (in W), at the estimate
    #: the set was chosen at (:meth:`chosen_at`): the directions the lateral residual's means are taken along
    #: (lrfcal.model.coverage.centred), data like ``lateral`` (None: not chosen yet, each return's own offset)
    axes: FloatArray | None = None

    @property
    def model(self) -> MarkerModel:
        """The model variant (the sensor's)."""
        return self.sensor.model

    @property
    def radius(self) -> float:
        """The marker radius R_m [m] (the sensor's)."""
        return self.sensor.radius_m

    @property
    def divergence(self) -> float:
        """The beam's full divergence [rad] (the sensor's)."""
        return self.sensor.divergence_rad

    @property
    def footprint(self) -> FloatArray:
        """(K,) footprint radius at each return's marker, in marker radii (k of :func:`footprint_depth`), from the
        measured range (data, not a function of the unknowns)."""
        return footprint_radius_m(self.r, self.divergence) / self.radius

    @property
    def sigma_lat(self) -> FloatArray:
        """(K,) spread of each return's beam axis about its marker's centre, per component: R_m sqrt(1 + k^2) / 2
        (module docstring)."""
        return 0.5 * self.radius * np.sqrt(1.0 + self.footprint ** 2)

    @property
    def n_res(self) -> int:
        """Residual components per return (4 for the sphere: 1 range + 3 lateral, 3 independent)."""
        return 3 if self.model == "paper" else 4

    def subset(self, m: NDArray[np.bool_]) -> MarkerSet:
        """The returns ``m`` (K,)."""
        return replace(self, lam=self.lam[m], mu=self.mu[m], r=self.r[m], c=self.c[m],
                       times=None if self.times is None else self.times[m],
                       marker=None if self.marker is None else self.marker[m],
                       scan=None if self.scan is None else self.scan[m],
                       beam=None if self.beam is None else self.beam[m],
                       lateral=None if self.lateral is None else self.lateral[m],
                       across=None if self.across is None else self.across[m],
                       axes=None if self.axes is None else self.axes[m])

    @property
    def n_independent(self) -> int:
        """Independent residuals: 3 per return for the paper's model; for the sphere, 1 per return (its range),
        plus, where the lateral residual is used, 1 per scan line (its in-plane mean) and 1 per crossing (its mean
        across the scan plane, unless only the in-plane part is kept) (:meth:`dof`)."""
        if self.model == "paper":
            return 3 * self.r.size
        return round(float(self.dof().sum()))

    @cached_property
    def coverage(self) -> Coverage | None:
        """The returns' scan lines and crossings (lrfcal.model.coverage), whose means the sphere's lateral residual
        keeps; None for the paper's model, or without the returns' markers and times, or where neither their scans
        nor their times tell lines apart (returns made up without a scan: each return's own offset)."""
        if self.model != MarkerModel.SPHERE or self.marker is None or self.times is None or not self.r.size:
            return None
        if np.ptp(self.times) == 0 and (self.scan is None or np.ptp(self.scan) == 0):
            return None
        return Coverage.of(self.marker, self.times, self.scan)

    def return_dof(self) -> FloatArray:
        """(K,) independent residuals of each return's own rows (``marker_rows(..., centred=False)``): 3 (the
        paper's, or the sphere's range and 2 lateral), 2 where the lateral residual keeps only its in-plane part, 1
        where it is not used."""
        if self.model == "paper":
            return np.full(self.r.size, 3.0)
        return np.where(self._lateral, np.where(self._in_plane_only, 2.0, 3.0), 1.0)

    @property
    def centring(self) -> tuple[Coverage, FloatArray] | None:
        """The coverage whose means the lateral rows keep (:attr:`coverage`) and the directions they are taken along
        (``axes``), once the set is chosen at an estimate (:meth:`chosen_at`); None before (each return's own
        offset)."""
        cov = self.coverage
        return None if self.axes is None or cov is None else (cov, self.axes)

    def lateral_means(self, res: FloatArray, J: FloatArray) -> tuple[tuple[FloatArray, FloatArray, int], ...]:
        """The lateral means among this set's rows ``res`` (K, n_res) and Jacobian ``J`` (K, n_res, p), where the
        lateral rows keep them (:attr:`centring`; else none), one whitened residual per crossing for each part: the
        crossing's mean across the scan plane, and the mean of its lines' means along it, each times the root of
        its lines (C,) and its Jacobian (C, p). The lines of one crossing share their in-plane mean's error (the
        beams' bearings against the marker's: the same in every line while the plane tilts across the marker), so a
        crossing is the unit of both. Their sigma, R_m sqrt(1 + k^2) / 2 over the root of the lines (or beams)
        averaged, is the most such a mean can miss the centre by; lines and beams at a regular spacing miss it by
        far less, and lrfcal.estimate.scatter measures by how much from these residuals' own scatter."""
        if self.centring is None:
            return ()
        cov, axes = self.centring
        lat = self._lateral
        out: list[tuple[FloatArray, FloatArray, int]] = []
        # a return's row holds its crossing's (line's) mean times sqrt(L / K_crossing) (1 / sqrt(K_line)): these
        # weights sum each crossing's rows to sqrt(L) times the mean of its lines' means
        for axis, keep, weight in ((axes[:, 0], lat & ~self._in_plane_only, 1.0 / np.sqrt(cov.per_crossing)),
                                   (axes[:, 1], lat, 1.0 / np.sqrt(cov.per_line * cov.lines_in_crossing))):
            if not np.any(keep):
                continue
            ids, unit = np.unique(cov.crossing[keep], return_inverse=True)
            w = weight[keep]
            rows = (res[keep, 1:] * axis[keep]).sum(1) * w
            Jr = np.einsum("ki,kij->kj", axis[keep], J[keep, 1:]) * w[:, None]
            z = np.bincount(unit, rows, ids.size).astype(np.float64)
            Jz = np.stack([np.bincount(unit, Jr[:, j], ids.size) for j in range(Jr.shape[1])], 1).astype(np.float64)
            out.append((z, Jz, int(ids.size)))
        return tuple(out)

    def dof(self) -> FloatArray:
        """(K,) independent residuals of each return (:attr:`n_independent`): :meth:`return_dof`, but where the
        lateral residual keeps its lines' and crossings' means (:attr:`centring`), the return's share of them."""
        if self.centring is None:
            return self.return_dof()
        cov = self.centring[0]
        return 1.0 + np.where(self._lateral, cov.lateral_dof(~self._in_plane_only), 0.0)

    @property
    def _lateral(self) -> NDArray[np.bool_]:
        return np.ones(self.r.size, bool) if self.lateral is None else self.lateral

    @property
    def _in_plane_only(self) -> NDArray[np.bool_]:
        return np.zeros(self.r.size, bool) if self.across is None else np.any(self.across != 0.0, axis=1)

    # -- the observation set (lrfcal.model.observations.ObservationSet) --

    @property
    def size(self) -> int:
        """The number of returns K."""
        return int(self.r.size)

    @property
    def n_nuisance(self) -> int:
        """No nuisances: the marker centres are the map's (their uncertainty is carried, not estimated)."""
        return 0

    @property
    def min_kept(self) -> int:
        """The robust passes stop before keeping fewer than 4 marker returns."""
        return 4

    def blocks(self, th: FloatArray, R_ref: FloatArray, ctx: RowContext, jac: bool = True) -> Blocks:
        """The whitened residuals (K n_res,) as dense rows, and their Jacobian (K n_res, N_CORE)
        (:func:`marker_rows`)."""
        if not self.r.size:
            return Blocks.dense(np.zeros(0), np.zeros((0, N_CORE)))
        res, J = marker_rows(th, self, ctx.sigma_r, R_ref, jac=jac, clock=ctx.clock, mount_jac=ctx.mount_jac,
                             chart=ctx.chart)
        return Blocks.dense(res.ravel(), None if J is None else J.reshape(-1, N_CORE))

    def chi(self, th: FloatArray, R_ref: FloatArray, ctx: RowContext) -> FloatArray:
        """(K,) each return's whitened residual norm over the square root of its independent components: its own
        offset from its marker, not its lines' means (:meth:`return_dof`): a return far off its marker is judged
        by where it is."""
        res, _ = marker_rows(th, self, ctx.sigma_r, R_ref, jac=False, clock=ctx.clock, mount_jac=ctx.mount_jac,
                             centred=False)
        return np.sqrt((res**2).sum(1) / self.return_dof())

    def kept(self, th: FloatArray, R_ref: FloatArray, ctx: RowContext, keep: NDArray[np.bool_]
             ) -> NDArray[np.bool_]:
        """(K,) the returns whose :meth:`chi` is within 4 robust sigma, the scale from the median of chi^2 of the
        returns ``keep`` over chi2_3's (:data:`CHI2_3_MEDIAN`), never below 1."""
        return robust_kept(self.chi(th, R_ref, ctx), keep, CHI2_3_MEDIAN, squared=True)

    def chosen_at(self, th: FloatArray, R_ref: FloatArray, ctx: RowContext) -> MarkerSet:
        """The set with the lateral residuals of the markers the scan plane crosses on one side only left out,
        and in the model variant ``in_plane_at_turns`` only their in-plane part in crossings that turn on their
        marker (:func:`crossings`, at th); and the directions its lateral means are taken along (``axes``, at th)."""
        turns = self.in_plane_at_turns
        lateral, across, axes = _chosen(th, self, R_ref, ctx.clock, turns)
        return replace(self, lateral=lateral, across=across if turns else None, axes=axes)

    def clusters(self, first: int) -> tuple[NDArray[np.int64], NDArray[np.int64]]:
        """Each dense row's cluster: its return's crossing (the marker's successive scan lines,
        lrfcal.model.coverage.crossing_ids, numbered from ``first``): a crossing's lines share where they fall on
        the marker, so they count as one sample, not one each; without the returns' times, each scan's returns are
        one cluster."""
        if self.times is None or self.marker is None:
            assert self.scan is not None, "the covariance's clusters need the returns' times or scans"
            base = self.scan
        else:
            cov = self.coverage
            base = first + (cov.crossing if cov is not None else crossing_ids(self.marker, self.times))
        return np.repeat(base, self.n_res), np.zeros(0, dtype=np.int64)

    def groups(self) -> NDArray[np.int64] | None:
        """Each dense row's marker: the errors the returns of one marker share (lrfcal.estimate.covariance)."""
        return None if self.marker is None else np.repeat(self.marker, self.n_res)


def marker_rows(th: FloatArray, ms: MarkerSet, sigma_r: float, R_ref: FloatArray, *, jac: bool = True,
                clock: MotorClock | None = None, mount_jac: bool = True, chart: FloatArray | None = None,
                centred: bool = True) -> tuple[FloatArray, FloatArray | None]:
    """Whitened residuals (K, n_res) and their Jacobian (K, n_res, N_CORE) (None when jac is False) at th;
    ``chart``: what the scan-plane columns are derivatives by (lrfcal.model.rays.beam_rays). The sphere's lateral
    rows keep their lines' and crossings' means (lrfcal.model.coverage.centred, where the set has its returns'
    markers and times); ``centred=False``: each return's own offset (the robust pass judges a return by it)."""
    motor = motor_angles(th, ms.lam, ms.times, clock)
    o, d, Jo, Jd = beam_rays(th, R_ref, motor, ms.mu, jac=jac, mount_jac=mount_jac, chart=chart)
    if ms.model == "paper":  # the return point: the true range of the reported one
        rng = true_range(th, ms.r, on_marker=True)
        r = rng.r
        res = (o + r[:, None] * d - ms.c) / sigma_r
        if Jo is None or Jd is None:
            return res, None
        J = (Jo + r[:, None, None] * Jd) / sigma_r
        for j, dr in rng.partials:
            J[:, :, j] = dr[:, None] * d / sigma_r
        return res, J
    R = ms.radius
    v, t, e = ray_to_centre(o, d, ms.c)
    rho = np.linalg.norm(e, axis=1)
    s, ds = footprint_depth(rho / R, ms.footprint)
    # where the beam meets the sphere: for the bias where it is not 0, or for its Jacobian column
    inc, dinc = footprint_incidence(rho / R, ms.footprint) if jac or th[INC] != 0.0 else (None, None)
    # the range the scanner reports of r_hat = t - R s, met at the incidence inc
    rep = reported_range(th, t - R * s, on_marker=True, incidence=inc)
    sig_lat = ms.sigma_lat[:, None]
    res = np.concatenate([((ms.r - rep.r) / sigma_r)[:, None], e / sig_lat], 1)
    if ms.lateral is not None:
        res[~ms.lateral, 1:] = 0.0
    if ms.across is not None:
        res[:, 1:] = _in_plane(res[:, 1:], ms.across)
    centring = ms.centring if centred else None
    if centring is not None:
        cov, axes = centring
        res[:, 1:] = centred_rows(res[:, 1:], axes[:, 0], axes[:, 1], cov)
    if Jo is None or Jd is None:
        return res, None
    Jv = -Jo
    Jt = np.einsum("kij,ki->kj", Jv, d) + np.einsum("ki,kij->kj", v, Jd)
    Je = Jv - d[:, :, None] * Jt[:, None, :] - t[:, None, None] * Jd
    n_e = e / np.maximum(rho, 1e-15)[:, None]
    Jrho = np.einsum("ki,kij->kj", n_e, Je)
    Jrhat = Jt - ds[:, None] * Jrho
    J = np.concatenate([(-rep.scale * Jrhat / sigma_r)[:, None, :], Je / sig_lat[:, :, None]], 1)
    if th[INC] != 0.0 and dinc is not None:  # the incidence's own change: d inc = dinc d rho / R
        J[:, 0, :] -= (th[INC] * dinc / (R * sigma_r))[:, None] * Jrho
    for j, dr in rep.partials:
        J[:, 0, j] = -dr / sigma_r
    if ms.lateral is not None:
        J[~ms.lateral, 1:] = 0.0
    if ms.across is not None:
        J[:, 1:] = _in_plane(J[:, 1:], ms.across)
    if centring is not None:
        J[:, 1:] = centred_rows(J[:, 1:], axes[:, 0], axes[:, 1], cov)
    return res, J


def _plane_axes(th: FloatArray, R_ref: FloatArray, motor: MotorAngles, mu: FloatArray
                ) -> tuple[FloatArray, FloatArray, FloatArray]:
    """The rays' origins (K, 3), the scan plane's unit normal (K, 3, the scanner's z axis) and the unit direction in
    it across each ray (K, 3), in W: the normal from the ray and the one a quarter turn further in the scan
    (lrfcal.model.rays.beam_rays)."""
    o, d, _, _ = beam_rays(th, R_ref, motor, mu, jac=False)
    _, d2, _, _ = beam_rays(th, R_ref, motor, mu + 0.5 * np.pi, jac=False)
    c = np.cross(d, d2)
    n = c / np.linalg.norm(c, axis=1)[:, None]
    return o, n, np.cross(n, d)


def _in_plane(lateral: FloatArray, across: FloatArray) -> FloatArray:
    """Lateral rows (K, 3) or their Jacobian (K, 3, p) without their component along ``across`` (K, 3): the scan
    plane's normal where only the in-plane part is used, 0 elsewhere (taken as data, judged at each pass's
    estimate like the lateral mask, so the derivative of the normal itself does not enter)."""
    if lateral.ndim == 2:
        return lateral - (lateral * across).sum(1)[:, None] * across
    return lateral - across[:, :, None] * np.einsum("ki,kij->kj", across, lateral)[:, None, :]


def centre_jacobian(th: FloatArray, ms: MarkerSet, sigma_r: float, R_ref: FloatArray,
                    clock: MotorClock | None = None) -> FloatArray:
    """(K, n_res, 3): the whitened residuals' derivatives with respect to each return's marker centre c (in W).

    paper: -I / sigma_r. sphere (v = c - o, so v_c = I): t_c = d^T, e_c = I - d d^T, |e|_c = (e / |e|)^T (e is
    normal to d), r_hat_c = d^T - s'(u) (e / |e|)^T; range row -range_scale r_hat_c / sigma_r, lateral rows
    e_c / sigma_lat."""
    motor = motor_angles(th, ms.lam, ms.times, clock)
    o, d, _, _ = beam_rays(th, R_ref, motor, ms.mu, jac=False)
    K = ms.r.size
    if ms.model == "paper":
        return np.broadcast_to(-np.eye(3) / sigma_r, (K, 3, 3)).copy()
    R = ms.radius
    _, _, e = ray_to_centre(o, d, ms.c)
    rho = np.linalg.norm(e, axis=1)
    _, ds = footprint_depth(rho / R, ms.footprint)
    n_e = e / np.maximum(rho, 1e-15)[:, None]
    Ec = np.eye(3) - d[:, :, None] * d[:, None, :]
    r_hat_c = d - ds[:, None] * n_e
    Jc = np.concatenate([(-th[RSCALE] * r_hat_c / sigma_r)[:, None, :], Ec / ms.sigma_lat[:, None, None]], 1)
    if ms.lateral is not None:
        Jc[~ms.lateral, 1:] = 0.0
    if ms.across is not None:
        Jc[:, 1:] = _in_plane(Jc[:, 1:], ms.across)
    if ms.centring is not None:  # the rows' means (marker_rows): each group is one marker's
        cov, axes = ms.centring
        Jc[:, 1:] = centred_rows(Jc[:, 1:], axes[:, 0], axes[:, 1], cov)
    return Jc


def two_sided(th: FloatArray, ms: MarkerSet, R_ref: FloatArray, clock: MotorClock | None = None
              ) -> NDArray[np.bool_]:
    """(K,) whether each return's marker is crossed by the scan plane on both sides of its centre
    (:func:`crossings`' first part)."""
    return crossings(th, ms, R_ref, clock, turns=False)[0]


def crossings(th: FloatArray, ms: MarkerSet, R_ref: FloatArray, clock: MotorClock | None = None,
              turns: bool = True) -> tuple[NDArray[np.bool_], FloatArray]:
    """Which part of each return's lateral residual is used: (K,) whether its marker is crossed by the scan plane on
    both sides of its centre (else none of it), and (K, 3) the scan plane's unit normal where only its part in
    the scan plane is (a crossing that turns on its marker, lrfcal.model.coverage.turning), 0 elsewhere (everywhere
    when not ``turns``: only the first part is wanted).

    A return's lateral residual says "the marker's centre is on my ray, give or take a filled disc": unbiased
    when the scan lines that hit the marker pass on both sides of its centre. A marker the scan plane only grazes
    (at the edge of the band a tilted plane sweeps, or seen by one line) is hit on one cap only, and the mean of its
    lateral offsets is not its centre: a spinning scan plane tilted 28 deg came back 4 sigma off in alpha that way.
    Its returns keep their range residual; their lateral one is dropped (MarkerSet.lateral). The side of a return
    is the sign of the centre's distance from the scan plane, (c - o) . z_L, z_L the scanner's axis in W."""
    return _chosen(th, ms, R_ref, clock, turns)[:2]


def _chosen(th: FloatArray, ms: MarkerSet, R_ref: FloatArray, clock: MotorClock | None, turns: bool
            ) -> tuple[NDArray[np.bool_], FloatArray, FloatArray | None]:
    """:func:`crossings`' two parts and the directions the set's lateral means are taken along (MarkerSet.axes;
    None without its coverage), from one evaluation of the rays."""
    if ms.model != MarkerModel.SPHERE or ms.marker is None or ms.r.size == 0:
        return np.ones(ms.r.size, dtype=bool), np.zeros((ms.r.size, 3)), None
    motor = motor_angles(th, ms.lam, ms.times, clock)
    o, n, along = _plane_axes(th, R_ref, motor, ms.mu)
    h = ((ms.c - o) * n).sum(1)
    side = np.sign(h)
    lo = np.full(int(ms.marker.max()) + 1, 2.0)
    hi = np.full(lo.size, -2.0)
    np.minimum.at(lo, ms.marker, side)
    np.maximum.at(hi, ms.marker, side)
    both = (lo < 0)[ms.marker] & (hi > 0)[ms.marker]
    turns_on = (turning(h, ms.marker, ms.times, ms.radius) if turns and ms.times is not None
                else np.zeros(h.size, bool))
    axes = None if ms.coverage is None else np.stack([n, along], 1)
    return both, np.where(turns_on[:, None], n, 0.0), axes


def residuals_3d(params: Params, ranges_m: ArrayLike, lambda_rad: ArrayLike, mu_rad: ArrayLike, centres_W: ArrayLike,
                 *, model: str, marker_radius_m: float) -> FloatArray:
    """3D residual (K, 3) of K returns: paper: p - c (return point minus marker centre); sphere:
    (p - c)(1 - R / |p - c|), the return point minus the nearest point of the marker's surface (norm = ||p - c| - R|).
    """
    p = transform_points(params.mount.matrix(), points_M(ranges_m, lambda_rad, mu_rad, params.dh))
    diff = p - np.asarray(centres_W, dtype=float)
    if model == "sphere":
        dist = np.linalg.norm(diff, axis=1)
        diff = diff * (1.0 - marker_radius_m / np.maximum(dist, 1e-15))[:, None]
    return diff


__all__ = ["CHI2_3_MEDIAN", "MODELS", "MarkerModel", "MarkerSensor", "MarkerSet", "centre_jacobian", "crossings",
           "footprint_radius_m", "marker_rows",
           "ray_to_centre", "residuals_3d", "two_sided"]
