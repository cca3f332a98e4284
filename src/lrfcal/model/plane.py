"""Ray-plane range residuals and their Jacobian, row by row without (K, 3, N_CORE) temporaries.

A return k on plane j (:class:`PlaneSet`) has the residual (r_k - range_scale r_p - range_offset - incidence_bias
theta) / sigma_r (lrfcal.model.scanner.reported_range) against the ray-plane distance r_p = (d_j - n_j . o) /
(n_j . dir), theta = arccos |n_j . dir| the beam's incidence on the plane (lrfcal.estimate.solve's module docstring
has the forward model; the incidence's own derivatives: :func:`_add_incidence_change`).
Everything is evaluated in the frame of the beam before the motor's turn ("L0": M turned back by lambda_k), where
the ray is fixed by the DH parameters alone, o_0 = [a, -b sin alpha, b cos alpha] and
dir_0 = [cos phi, sin phi cos alpha, sin phi sin alpha] (phi = beta + mu_k), and the plane's normal is
n_0 = Rz(-lambda_k) R^T n_j (R the mount's rotation). Then, with nd = n_0 . dir_0 and x_0 = o_0 + r_p dir_0:

    n . o = n_0 . o_0 + n . t,   n . dir = nd,
    dr_p/dt = -n / nd,   dr_p/dw = (n_M x o_M + r_p n_M x d_M)^T J_r(w) / nd   (n_M = R^T n),
    dr_p/dk = -(n_0 . do_k + r_p dw_k . (dir_0 x n_0)) / nd   for a scan-plane unknown k with the chart column
        (do_k, dw_k) (lrfcal.model.chart; ddir_0 = dw_k x dir_0); for the DH parameters p in closed form,
        dr_p/dp = -(n_0 . do_0/dp + r_p n_0 . ddir_0/dp) / nd,
    dr_p/dlambda = -(n_0 . (z x o_0) + r_p n_0 . (z x dir_0)) / nd   (times each dlambda/dtheta, lrfcal.model.motor),
    dr_p/dd_j = 1 / nd,   dr_p/du_i = -(x_0 . Rz(-lambda) R^T dn/du_i + t . dn/du_i) / nd,
    dn/du_i = (t_i - n (n . t_i)) / |m|.

These are the same numbers as the chain rule through o and dir in W (lrfcal.model.rays), in O(K) work: the
plane returns of a targetless calibration are 10^5 and more rows.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from functools import cached_property

import numpy as np
from numpy.typing import NDArray

from lrfcal.model.kinematics import exp_so3, right_jacobian_so3
from lrfcal.model.motor import MotorAngles, MotorClock, motor_angles
from lrfcal.model.observations import Blocks, RowContext, robust_kept, robust_scale, within_cut
from lrfcal.model.range_pattern import PatternRows, pattern_rows, projected
from lrfcal.model.scanner import TrueBearing, reported_range, true_bearing
from lrfcal.model.unknowns import BSCALE, INC, N_CORE, SCALE

FloatArray = NDArray[np.float64]
_EYE = np.eye(3)


#: a plane whose robust scale at an estimate is this many times the planes' median (and at least the noise's) is
#: given up whole: it is not one flat surface (two taken as one: the room replica's desk top and the stand's base
#: board 2 cm above it, whitened scale 2.1 and flat-topped where the median plane's is 1.1-1.2; every plane of the
#: box replica, room_box and cardboard_box 1.00-1.06)
THICK = 1.6


@dataclass(frozen=True)
class Footing:
    """Where a plane return counts, judged at every estimate (the targetless cost's rule, lrfcal.stages.targetless):
    its beam meets its plane at a |cos| of at least ``min_cos`` (a plane seen edge-on reads short: the footprint
    spreads along it), and its ray meets the plane ``clearance_m`` or farther from every other plane (an edge or a
    corner mixes two surfaces)."""

    min_cos: float
    clearance_m: float


@dataclass(frozen=True)
class PlaneSet:
    """Non-marker returns (K2 rows) on P planes whose normals and offsets are nuisance parameters: an observation
    set (lrfcal.model.observations.ObservationSet).

    Plane j: n_j = m_j / |m_j|, m_j = n0_j + u1_j t1_j + u2_j t2_j (t1, t2 tangent to the initial normal n0),
    n_j . p = d_j. The nuisance vector follows the core unknowns: (u1, u2, d) per plane.
    """

    lam: FloatArray
    mu: FloatArray
    r: FloatArray
    plane: NDArray[np.int64]  # (K2,) plane index
    n0: FloatArray  # (P, 3)
    t1: FloatArray  # (P, 3)
    t2: FloatArray  # (P, 3)
    prior_mean: FloatArray | None = None  # (3P,) nuisance values the markers give
    prior_sigma: FloatArray | None = None  # (3P,) their uncertainty (None: free planes)
    times: FloatArray | None = None  # (K2,) laser-clock beam times (for the clock offset)
    prior_jacobian: FloatArray | None = None  # (3P, 3n) d prior_mean / d marker coordinates (the map's uncertainty)
    scan: NDArray[np.int64] | None = None  # (K2,) each return's scan (each scan's returns one cluster)
    beam: NDArray[np.int64] | None = None  # (K2,) each return's beam in its scan (the range noise's neighbours)
    footing: Footing | None = None  # where a return counts, judged at every estimate (None: every return may)
    #: (K2,) each return's bin of beams for the range pattern along the scan (lrfcal.model.range_pattern), a nuisance
    #: of the cost eliminated beside the core unknowns (None: no pattern)
    pattern_bins: NDArray[np.int64] | None = None

    def subset(self, m: NDArray[np.bool_]) -> PlaneSet:
        """The returns ``m`` (K2,) (on the same planes); the cos and sin computed so far carried over (elementwise:
        those of the subset are the subset of these)."""
        out = replace(self, lam=self.lam[m], mu=self.mu[m], r=self.r[m], plane=self.plane[m],
                      times=None if self.times is None else self.times[m],
                      scan=None if self.scan is None else self.scan[m],
                      beam=None if self.beam is None else self.beam[m],
                      pattern_bins=None if self.pattern_bins is None else self.pattern_bins[m])
        for name in ("trig_lam", "trig_mu"):
            if name in self.__dict__:  # a cached_property computed on this set
                c, s = self.__dict__[name]
                out.__dict__[name] = (c[m], s[m])
        return out

    @property
    def n_planes(self) -> int:
        return int(self.n0.shape[0])

    @cached_property
    def trig_lam(self) -> tuple[FloatArray, FloatArray]:
        """cos and sin (K2,) of the declared motor angles ``lam`` (computed once: lrfcal.model.plane)."""
        return np.cos(self.lam), np.sin(self.lam)

    @cached_property
    def trig_mu(self) -> tuple[FloatArray, FloatArray]:
        """cos and sin (K2,) of the declared bearings ``mu`` (computed once: lrfcal.model.plane)."""
        return np.cos(self.mu), np.sin(self.mu)

    @cached_property
    def _plane_runs(self) -> NDArray[np.int64] | None:
        """How many rows each plane has (P,) when the rows are in plane order (as lrfcal.stages.surfaces makes them),
        else None."""
        pl = self.plane
        if pl.size and not (pl[0] >= 0 and pl[-1] < self.n_planes and bool(np.all(pl[1:] >= pl[:-1]))):
            return None
        return np.bincount(pl, minlength=self.n_planes)

    def per_row(self, v: FloatArray) -> FloatArray:
        """Per-plane values v (P,) at each row (K2,), v[plane]: by repeating each plane's value over its run of rows
        where the rows are in plane order (a copy, faster than the gather), else by the gather."""
        runs = self._plane_runs
        return v[self.plane] if runs is None else np.repeat(v, runs)

    @cached_property
    def segments(self) -> tuple[NDArray[np.int64], NDArray[np.int64]]:
        """The rows in a stable order by plane (K2,) and each plane's [start, stop) in it (P + 1,)."""
        order = np.argsort(self.plane, kind="stable")
        return order, np.searchsorted(self.plane[order], np.arange(self.n_planes + 1))


    # -- the observation set (lrfcal.model.observations.ObservationSet) --

    @property
    def size(self) -> int:
        """The number of returns K2."""
        return int(self.r.size)

    @property
    def n_nuisance(self) -> int:
        """3 per plane: (u1, u2, d)."""
        return 3 * self.n_planes

    @property
    def n_independent(self) -> int:
        """One per return, and one per prior row (3 per plane with the markers' prior)."""
        return self.size + (0 if self.prior_sigma is None else int(self.prior_sigma.size))

    @property
    def min_kept(self) -> int:
        """No minimum of its own (a solve checks its returns per unknown before it starts)."""
        return 0

    def blocks(self, th: FloatArray, R_ref: FloatArray, ctx: RowContext, jac: bool = True) -> Blocks:
        """The ray-plane rows (:func:`plane_rows`) and the planes' priors (th_nu - prior_mean) / prior_sigma."""
        rows = plane_rows(th, self, ctx.sigma_r, R_ref, jac=jac, clock=ctx.clock, mount_jac=ctx.mount_jac,
                          chart=ctx.chart, incidence_jac=ctx.incidence_jac)
        r_q = w_q = None
        if self.prior_sigma is not None and self.prior_mean is not None:  # the markers' word on the planes
            r_q, w_q = (th[N_CORE:] - self.prior_mean) / self.prior_sigma, 1.0 / self.prior_sigma
        J_d = np.zeros((0, N_CORE))
        pattern = self.pattern(ctx)
        res = rows.res if pattern is None else projected(rows.res, pattern)
        return Blocks(np.zeros(0), J_d, res, rows.Jc, rows.Jn, self.plane, self.n_planes, r_q, w_q,
                      self.segments, pattern)

    def pattern(self, ctx: RowContext) -> PatternRows | None:
        """The rows' range pattern along the scan (None: the set has none)."""
        return None if self.pattern_bins is None else pattern_rows(self.pattern_bins, ctx.sigma_r)

    def kept(self, th: FloatArray, R_ref: FloatArray, ctx: RowContext, keep: NDArray[np.bool_]
             ) -> NDArray[np.bool_]:
        """(K2,) the returns whose |whitened residual| is within 4 robust sigma, the scale the median absolute
        residual of the returns ``keep`` over the normal distribution's (0.674, the MAD), never below 1; with a
        :class:`Footing` (the targetless cost), each plane's returns by the scale of its own, none of a plane whose
        scale is :data:`THICK` times the planes' median, and only those whose beam meets their plane where it counts
        at th (:func:`footing`)."""
        rs = np.abs(plane_rows(th, self, ctx.sigma_r, R_ref, jac=False, clock=ctx.clock).res)
        if self.footing is None:
            return robust_kept(rs, keep, 0.674, squared=False)
        kept = np.zeros(self.size, dtype=bool)
        order, bounds = self.segments
        scale = np.full(self.n_planes, np.nan)
        for j in range(self.n_planes):  # each plane by its own scale: a rougher one is not given up whole
            rows = order[bounds[j]:bounds[j + 1]]
            if rows.size and keep[rows].any():
                scale[j] = robust_scale(rs[rows], keep[rows], 0.674, squared=False)
                kept[rows] = within_cut(rs[rows], scale[j])  # as robust_kept, the scale kept
        if np.isfinite(scale).any():  # but one far thicker than the others is no one flat surface: given up
            thick = np.flatnonzero(scale > THICK * max(1.0, float(np.nanmedian(scale))))
            kept[np.isin(self.plane, thick)] = False
        cos_incidence, clear_m = footing(th, self, R_ref, ctx.clock)
        return kept & (cos_incidence >= self.footing.min_cos) & (clear_m >= self.footing.clearance_m)

    def chosen_at(self, th: FloatArray, R_ref: FloatArray, ctx: RowContext) -> PlaneSet:
        """The same set: every plane return's one residual counts at every estimate (the surface returns chosen
        again are a new set, built by the stage: lrfcal.stages.surfaces)."""
        return self

    def clusters(self, first: int) -> tuple[NDArray[np.int64], NDArray[np.int64]]:
        """Each plane row's cluster: its scan (the errors shared by a scan's returns: its motor angle)."""
        assert self.scan is not None, "the covariance's clusters need the plane returns' scans"
        return np.zeros(0, dtype=np.int64), self.scan

    def groups(self) -> NDArray[np.int64] | None:
        """No dense rows."""
        return None


@dataclass(frozen=True)
class PlaneRows:
    """Whitened residuals res (K,) of plane returns and, with the Jacobian, its core block Jc (K, N_CORE) and each
    row's own plane's nuisance block Jn (K, 3) (columns N_CORE + 3 plane + (0, 1, 2) of the full Jacobian)."""

    res: FloatArray
    Jc: FloatArray | None = None
    Jn: FloatArray | None = None


def plane_rows(th: FloatArray, s: PlaneSet, sigma_r: float, R_ref: FloatArray, *, jac: bool = True,
               clock: MotorClock | None = None, mount_jac: bool = True, chart: FloatArray | None = None,
               incidence_jac: bool = True) -> PlaneRows:
    """The plane returns' whitened residuals and Jacobian blocks at th (N_CORE + 3P,) (module docstring).

    ``clock``: the clock offset is an unknown (its column is 0 otherwise); ``mount_jac`` False leaves the mount's
    columns 0 (a held mount); ``chart`` (6, 4): what the scan-plane columns are derivatives by (None: the DH
    parameters); ``incidence_jac`` False leaves the incidence bias's column 0 while the bias is 0 (held and not
    tested). Per-plane quantities are gathered to the rows as scalars (K,), and the Jacobian blocks are column-major:
    both keep the work a few passes over (K,) arrays."""
    geo = _rays_on_planes(th, s, R_ref, clock)
    n_p, motor, pl = geo.n_p, geo.motor, s.per_row
    a, b, ca, sa, cp, sp, cl, sl = geo.a, geo.b, geo.ca, geo.sa, geo.cp, geo.sp, geo.cl, geo.sl
    nx, ny, nz, oy, oz, dy, dz, nd, rp = geo.nx, geo.ny, geo.nz, geo.oy, geo.oz, geo.dy, geo.dz, geo.nd, geo.rp
    bearing = geo.bearing
    # the beam's incidence on its plane: where the bias is not 0, or for its Jacobian column (an arccos of every row,
    # left out while the bias is 0 and its column is not asked for)
    incidence = (np.arccos(np.minimum(np.abs(nd), 1.0)) if (jac and incidence_jac) or th[INC] != 0.0 else None)
    rep = reported_range(th, rp, on_marker=False, incidence=incidence)
    res = (s.r - rep.r) / sigma_r
    if not jac:
        return PlaneRows(res)
    K = s.r.size
    k = -rep.scale / sigma_r  # the residual's Jacobian is -scale dr_p / sigma_r
    q = k / nd  # (K,)
    Jc = np.zeros((K, N_CORE), order="F")
    xx, xy, xz = a + rp * cp, oy + rp * dy, oz + rp * dz  # x_0 = o_0 + r_p dir_0
    if mount_jac:
        for i in range(3):
            Jc[:, i] = -pl(n_p[:, i]) * q
        # n_M x x_M = Rz(lambda) (n_0 x x_0)
        cx, cy, cz = ny * xz - nz * xy, nz * xx - nx * xz, nx * xy - ny * xx
        cMx, cMy = cl * cx - sl * cy, sl * cx + cl * cy
        Jr = right_jacobian_so3(th[3:6])
        for j in range(3):
            Jc[:, 3 + j] = (cMx * Jr[0, j] + cMy * Jr[1, j] + cz * Jr[2, j]) * q
    if chart is None:  # the DH parameters: the chart columns below in closed form
        Jc[:, 6] = -nx * q
        Jc[:, 7] = (ny * b * ca + nz * b * sa + rp * sp * (ny * sa - nz * ca)) * q
        Jc[:, 8] = (ny * sa - nz * ca) * q
        Jc[:, 9] = turn = -rp * (-nx * sp + (ny * ca + nz * sa) * cp) * q
    else:
        g = _dir_x_normal(geo)
        for k in range(4):
            Jc[:, 6 + k] = -(_dot(chart[:3, k], (nx, ny, nz)) + rp * _dot(chart[3:, k], g)) * q
        turn = -rp * _dot((0.0, -sa, ca), g) * q
    for j, dmu in bearing.partials:  # the bearing enters as beta does: a turn about the scanner's axis
        Jc[:, j] = turn * dmu
    if motor.partials:  # dr_p/dlambda = -(n_0 . (z x x_0)) / nd, z x v = (-v_y, v_x, 0)
        dres_dlam = -((ny * a - nx * oy) + rp * (ny * cp - nx * dy)) * q
        for j, dlam in motor.partials:
            Jc[:, j] = dres_dlam * dlam
    for j, dr in rep.partials:
        Jc[:, j] = -dr / sigma_r
    Jn = np.empty((K, 3), order="F")
    for i, tan in enumerate((s.t1, s.t2)):
        (ux, uy, uz), shift = _normal_turn(s, geo, tan)
        Jn[:, i] = -(xx * ux + xy * uy + xz * uz + shift) * q
    Jn[:, 2] = q
    if th[INC] != 0.0:  # the incidence's own change with the unknowns
        assert incidence is not None
        _add_incidence_change(th, geo, incidence, sigma_r, Jc, Jn, s, mount_jac, chart)
    return PlaneRows(res, Jc, Jn)


def _dir_x_normal(geo: _RaysOnPlanes) -> tuple[FloatArray, FloatArray, FloatArray]:
    """dir_0 x n_0 per row (3 x (K,)): a turn dw of the ray changes n_0 . dir_0 by dw . (dir_0 x n_0)."""
    return (geo.dy * geo.nz - geo.dz * geo.ny, geo.dz * geo.nx - geo.cp * geo.nz, geo.cp * geo.ny - geo.dy * geo.nx)


def _normal_turn(s: PlaneSet, geo: _RaysOnPlanes, tan: FloatArray
                 ) -> tuple[tuple[FloatArray, FloatArray, FloatArray], FloatArray]:
    """How each row's plane normal moves with its nuisance along the tangent ``tan`` (P, 3): dn/du in L0,
    Rz(-lambda) R^T dn/du (3 x (K,)), and dn/du . t (K,), dn/du = (tan - n (n . tan)) / |m| (module docstring)."""
    pl = s.per_row
    dn = (tan - geo.n_p * (geo.n_p * tan).sum(1, keepdims=True)) / geo.m_norm  # (P, 3) in W
    vM = dn @ geo.R
    gx, gy = pl(vM[:, 0]), pl(vM[:, 1])
    return (geo.cl * gx + geo.sl * gy, geo.cl * gy - geo.sl * gx, pl(vM[:, 2])), pl(dn @ geo.t)


def _add_incidence_change(th: FloatArray, geo: _RaysOnPlanes, incidence: FloatArray, sigma_r: float, Jc: FloatArray,
                          Jn: FloatArray, s: PlaneSet, mount_jac: bool, chart: FloatArray | None) -> None:
    """Adds -incidence_bias d theta / sigma_r to the Jacobian blocks, theta = arccos |nd| (nd = n_0 . dir_0): nd
    changes with the directions alone (not a, b, the translation or the planes' offsets),
    d nd = n_0 . (dw x dir_0) = dw . (dir_0 x n_0) for a turn dw of the ray (alpha about x, beta and the bearing about
    the scanner's axis (0, -sin alpha, cos alpha), a chart column's dw_k), d nd / d lambda = n_y cos phi - n_x dir_y,
    d nd / dw_mount = -(n_M x d_M)^T J_r(w), d nd / du_i = dir_0 . Rz(-lambda) R^T dn/du_i."""
    nx, ny, cp, dy, dz, cl, sl = geo.nx, geo.ny, geo.cp, geo.dy, geo.dz, geo.cl, geo.sl
    sin_t = np.maximum(np.sin(incidence), 1e-9)
    f = th[INC] * np.sign(geo.nd) / (sin_t * sigma_r)  # -k d theta / sigma_r = f d nd (d theta = -sign d nd / sin)
    g = _dir_x_normal(geo)
    if mount_jac:
        cMx, cMy = -(cl * g[0] - sl * g[1]), -(sl * g[0] + cl * g[1])  # n_M x d_M = -Rz(lambda) g
        Jr = right_jacobian_so3(th[3:6])
        for j in range(3):
            Jc[:, 3 + j] -= f * (cMx * Jr[0, j] + cMy * Jr[1, j] - g[2] * Jr[2, j])
    turn_axis = (0.0, -geo.sa, geo.ca)
    if chart is None:
        Jc[:, 7] += f * g[0]
        Jc[:, 9] += f * (turn := _dot(turn_axis, g))
    else:
        for k in range(4):
            Jc[:, 6 + k] += f * _dot(chart[3:, k], g)
        turn = _dot(turn_axis, g)
    for j, dmu in geo.bearing.partials:
        Jc[:, j] += f * turn * dmu
    if geo.motor.partials:
        dnd_dlam = ny * cp - nx * dy
        for j, dlam in geo.motor.partials:
            Jc[:, j] += f * dnd_dlam * dlam
    for i, tan in enumerate((s.t1, s.t2)):
        (ux, uy, uz), _ = _normal_turn(s, geo, tan)
        Jn[:, i] += f * (cp * ux + dy * uy + dz * uz)



@dataclass(frozen=True)
class _RaysOnPlanes:
    """Every plane return's ray and its own plane at th, in the frame before the motor's turn (L0; module
    docstring): the planes' unit normals n_p (P, 3) in W and their norms before normalising (P, 1), the motor angles,
    the mount (t (3,), R (3, 3)), the DH's a, b and cos/sin of alpha, the rows' cos/sin of phi and lambda, n_0 =
    (nx, ny, nz), o_0 = (a, oy, oz), dir_0 = (cp, dy, dz), nd = n_0 . dir_0 and the ray-plane range r_p (all (K,)),
    and the bearing."""

    n_p: FloatArray
    m_norm: FloatArray
    motor: MotorAngles
    t: FloatArray
    R: FloatArray
    a: float
    b: float
    ca: float
    sa: float
    cp: FloatArray
    sp: FloatArray
    cl: FloatArray
    sl: FloatArray
    nx: FloatArray
    ny: FloatArray
    nz: FloatArray
    oy: float
    oz: float
    dy: FloatArray
    dz: FloatArray
    nd: FloatArray
    rp: FloatArray
    bearing: TrueBearing


def _rays_on_planes(th: FloatArray, s: PlaneSet, R_ref: FloatArray, clock: MotorClock | None) -> _RaysOnPlanes:
    """:class:`_RaysOnPlanes` at th (what :func:`plane_rows` and :func:`footing` share)."""
    P = s.n_planes
    nu = th[N_CORE:].reshape(P, 3)
    m = s.n0 + nu[:, :1] * s.t1 + nu[:, 1:2] * s.t2
    m_norm = np.linalg.norm(m, axis=1, keepdims=True)
    n_p = m / m_norm  # (P, 3) in W
    motor = motor_angles(th, s.lam, s.times, clock)
    lam = motor.lam
    t = th[:3]
    a, al, b, be = th[6:10]
    R = R_ref @ (_EYE if not th[3:6].any() else exp_so3(th[3:6]))  # exp_so3(0) is the identity, bit for bit
    ca, sa = np.cos(al), np.sin(al)
    bearing = true_bearing(th, s.mu)
    cp, sp = _cos_sin_sum(be, bearing.mu, s.trig_mu, th[BSCALE] == 1.0)  # phi = beta + mu_true
    cl, sl = _cos_sin_sum(0.0, lam, s.trig_lam, clock is None and th[SCALE] == 1.0)
    pl = s.per_row  # per-plane values (P,) gathered to the rows (K,)
    nM = n_p @ R  # (P, 3): R^T n per plane
    gx, gy = pl(nM[:, 0]), pl(nM[:, 1])
    nx, ny, nz = cl * gx + sl * gy, cl * gy - sl * gx, pl(nM[:, 2])  # n_0 = Rz(-lambda) R^T n
    oy, oz = -b * sa, b * ca  # o_0 = (a, oy, oz)
    dy, dz = sp * ca, sp * sa  # dir_0 = (cp, dy, dz)
    nd = nx * cp + ny * dy + nz * dz
    rp = (pl(nu[:, 2] - n_p @ t) - (nx * a + ny * oy + nz * oz)) / nd
    return _RaysOnPlanes(n_p, m_norm, motor, t, R, a, b, ca, sa, cp, sp, cl, sl, nx, ny, nz, oy, oz, dy, dz, nd, rp,
                         bearing)


def footing(th: FloatArray, s: PlaneSet, R_ref: FloatArray, clock: MotorClock | None = None
            ) -> tuple[FloatArray, FloatArray]:
    """Where each plane return's beam meets its own plane at th: |cos| of the angle between beam and normal (K,),
    and how far that point lies from the nearest other plane [m] (K,) (inf with one plane): a return on a plane seen
    edge-on reads short (its footprint spreads along the plane), and one whose ray meets its plane near another
    (an edge, a corner) mixes the two surfaces."""
    g = _rays_on_planes(th, s, R_ref, clock)
    x0 = (g.a + g.rp * g.cp, g.oy + g.rp * g.dy, g.oz + g.rp * g.dz)  # the ray's hit in L0
    nM = g.n_p @ g.R  # (P, 3)
    off = th[N_CORE:].reshape(s.n_planes, 3)[:, 2] - g.n_p @ g.t  # (P,): n . x = off in M
    clear = np.full(s.size, np.inf)
    for j in range(s.n_planes):
        nx = g.cl * nM[j, 0] + g.sl * nM[j, 1]
        ny = g.cl * nM[j, 1] - g.sl * nM[j, 0]
        d = np.abs(nx * x0[0] + ny * x0[1] + nM[j, 2] * x0[2] - off[j])
        np.minimum(clear, np.where(s.plane == j, np.inf, d), out=clear)
    return np.abs(g.nd), clear

def _dot(c: FloatArray | tuple[float, float, float], v: tuple[FloatArray, FloatArray, FloatArray]) -> FloatArray:
    """sum_i c_i v_i (K,) of a constant 3-vector c and three (K,) arrays."""
    return c[0] * v[0] + c[1] * v[1] + c[2] * v[2]


def _cos_sin_sum(c: float, x: FloatArray, trig: tuple[FloatArray, FloatArray], declared: bool
                 ) -> tuple[FloatArray, FloatArray]:
    """cos and sin of c + x (K,); where x is the declared angles themselves (``declared``: x unchanged by the
    unknowns), by the angle sum from their cached ``trig`` (a few multiplications, not two transcendental passes
    over the K rows)."""
    if not declared:
        return np.cos(c + x), np.sin(c + x)
    cx, sx = trig
    if c == 0.0:
        return cx, sx
    cc, sc = np.cos(c), np.sin(c)
    return cc * cx - sc * sx, sc * cx + cc * sx


__all__ = ["PlaneRows", "PlaneSet", "plane_rows"]
