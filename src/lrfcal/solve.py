"""Stage 6: Levenberg-Marquardt over the 10 parameters, and the laser-servo clock offset where the sweep shows it.

Unknowns (never Euler angles): the mount translation t = (x, y, z), the mount rotation on SO(3) as a reference
R_ref and a small rotation vector w applied in frame M (R = R_ref Exp(w); after every solver pass w is folded into
R_ref and restarts at 0, so the parameterisation has no singularity at any attitude), the DH parameters
(a, alpha, b, beta), and optionally the clock offset tau = laser stamp - servo stamp. Their order is
:data:`CORE_NAMES` (kinematics.ESTIMATE_NAMES + "clock_offset"); roll, pitch and yaw are only an output format.

Forward model (kinematics.py, eq. (3)), per return k at laser time t_k with bearing mu_k, range r_k,
phi_k = beta + mu_k and motor angle lambda_k = q(t_k - tau) (q: the joint states, interpolated linearly):

    o_M = Rz(lambda) [a, -b sin(alpha), b cos(alpha)]              beam origin in M
    d_M = Rz(lambda) [cos(phi), sin(phi) cos(alpha), sin(phi) sin(alpha)]   unit direction in M
    o = R o_M + t,  d = R d_M                                                  in W

Two observation models (c = the centre of the return's marker in W, R_m its radius):

* ``"paper"`` (seed paper eq. (10)): residual (o + r d - c) / sigma_r, 3 per return.
* ``"sphere"`` (every return on a marker, sub-beam): v = c - o, t = v.d, e = v - t d (|e| = distance of the
  centre from the ray), u = |e| / R_m,
      r_hat = t - R_m s(u),   s(u) = sqrt(eta softplus((1 - u^2) / eta))   (eta = 0.05)
  s(u) ~ sqrt(1 - u^2) (the depth of the sphere's surface below the centre plane) for u < ~0.97, and is
  smooth with bounded slope near and beyond the rim (s -> 0: a grazing or mixed-pixel return reports the
  rim). Residuals: (r - r_hat) / sigma_r and e / sigma_lat (3 components, one of them identically zero along
  d, hence 3 independent residuals per return), sigma_lat = R_m / 2 (hits spread uniformly over the visible
  disc: E|e|^2 = R_m^2 / 2).
  With a finite beam (``beam_divergence_rad`` delta > 0) the footprint at the marker is a disc of radius
  k R_m, k = r delta / (2 R_m) from the measured range r, and a retroreflector outshines whatever else it
  covers: s(u) becomes S(u, k), the mean of s over the part of the footprint that hits the sphere
  (footprint_depth), and sigma_lat = R_m sqrt(1 + k^2) / 2 (the beam's axis is the point hit on the marker's
  disc minus its offset within the footprint, two independent uniform discs). Modelling the beam
  as its axis alone leaves the footprint in the marker returns' ranges: on lrfsim's 4.4 mrad beam and 5 mm
  spheres a marker-return range bias of -0.9 mm (plane_30deg), +0.04 mm with the footprint (docs/study.md).

Analytic Jacobian (chain rule; dX/dtheta_j written X_j):
    translation: o_j = e_j, d_j = 0;
    rotation vector w_j: o_j = -R [o_M]x J_r(w) e_j, d_j = -R [d_M]x J_r(w) e_j (J_r: SO(3) right Jacobian);
    DH parameter p: o_j = R Rz(lambda) d(o_loc)/dp, d_j = R Rz(lambda) d(d_loc)/dp with
      d o_loc/da = (1,0,0), d o_loc/dalpha = (0, -b ca, -b sa), d o_loc/db = (0, -sa, ca), d o_loc/dbeta = 0,
      d d_loc/dalpha = (0, -sphi sa, sphi ca), d d_loc/dbeta = (-sphi, cphi ca, cphi sa), others 0;
    clock offset tau: o_tau = R (z x o_M) dlambda/dtau, d_tau = R (z x d_M) dlambda/dtau, dlambda/dtau = -omega(t_k -
      tau) (omega: the joint's angular velocity, smoothed over ~50 ms).
    paper: (o + r d)_j / sigma_r.
    sphere: v_j = -o_j; t_j = v_j.d + v.d_j; e_j = v_j - t_j d - t d_j; |e|_j = (e/|e|).e_j;
      r_hat_j = t_j - s'(u) |e|_j;  range residual_j = -r_hat_j / sigma_r;  lateral_j = e_j / sigma_lat.

Solver: a robust pass (trf, soft-L1 loss) from the start, then plain least squares with observations whose
whitened residual exceeds 4 sigma dropped (repeated until the inlier set is stable), whose Jacobian gives the
covariance s^2 (J^T J)^-1, s^2 the reduced chi-square of the whitened residuals. The plain passes, the targetless
solve and the information run on the normal equations with the planes' nuisances eliminated by the Schur complement
(lrfcal.normal_equations); the plane rows' Jacobian is lrfcal.model.plane's.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, replace

import numpy as np
from numpy.typing import ArrayLike, NDArray

from .errors import CalibrationError, InputError
from .model.kinematics import DH, Params, Pose, exp_so3, points_M, right_jacobian_so3, transform_points
from .model.plane import plane_rows
from .model.sphere import footprint_depth, sphere_depth
from .model.unknowns import (
    CORE_NAMES,
    MBIAS,
    N_CORE,
    ROFF,
    TAU,
    MotorClock,
    PlaneSet,
    motor_lambda,
    plane_nuisance_start,
)
from .normal_equations import RANK_TOL, Blocks, assemble, cluster_scores, levenberg_marquardt, schur
from .surfaces import Surface, SurfaceReturns
from .types import Observations, Solution

FloatArray = NDArray[np.float64]

MODELS = ("paper", "sphere")
_TAU, _ROFF, _MBIAS = TAU, ROFF, MBIAS
_Surf, _plane_nuisance_start, _lambda = PlaneSet, plane_nuisance_start, motor_lambda  # the names tests use
_DH_ANGLES = (7, 9)  # alpha, beta


def wrap_pi(a: ArrayLike) -> FloatArray:
    """Wrap angles to (-pi, pi]."""
    a = np.asarray(a, dtype=float)
    return a - 2 * np.pi * np.ceil((a - np.pi) / (2 * np.pi))


def _rays(
    core: FloatArray, R_ref: FloatArray, lam: FloatArray, mu: FloatArray, omega: FloatArray | None, jac: bool,
    mount_jac: bool = True,
) -> tuple[FloatArray, FloatArray, FloatArray | None, FloatArray | None]:
    """Beam origins o (K, 3) and unit directions d (K, 3) in W and their Jacobians (K, 3, N_CORE) with respect to
    the core unknowns (module docstring); the clock column is zero when ``omega`` is None, the mount's columns
    when ``mount_jac`` is False (a held mount)."""
    t, w = core[:3], core[3:6]
    a, al, b, be = core[6:10]
    lam, phi = np.broadcast_arrays(np.atleast_1d(lam), be + np.atleast_1d(mu))
    K = lam.size
    cl, sl = np.cos(lam), np.sin(lam)
    ca, sa = np.cos(al), np.sin(al)
    cp, sp = np.cos(phi), np.sin(phi)
    R = R_ref @ exp_so3(w)

    def rz(v: FloatArray) -> FloatArray:  # Rz(lambda_k) v_k for v (K, 3) or (3,)
        v = np.broadcast_to(v, (K, 3))
        return np.stack([cl * v[:, 0] - sl * v[:, 1], sl * v[:, 0] + cl * v[:, 1], v[:, 2]], -1)

    o_M = rz(np.array([a, -b * sa, b * ca]))
    d_M = rz(np.stack([cp, sp * ca, sp * sa], -1))
    o = o_M @ R.T + t
    d = d_M @ R.T
    if not jac:
        return o, d, None, None
    Jo = np.zeros((K, 3, N_CORE))
    Jd = np.zeros((K, 3, N_CORE))
    if mount_jac:
        Jo[:, 0, 0] = Jo[:, 1, 1] = Jo[:, 2, 2] = 1.0
        Jr = right_jacobian_so3(w)
        for j in range(3):
            Jo[:, :, 3 + j] = -np.cross(o_M, Jr[:, j]) @ R.T
            Jd[:, :, 3 + j] = -np.cross(d_M, Jr[:, j]) @ R.T
    z0 = np.zeros(K)
    Jo[:, :, 6] = rz(np.array([1.0, 0.0, 0.0])) @ R.T
    Jo[:, :, 7] = rz(np.array([0.0, -b * ca, -b * sa])) @ R.T
    Jo[:, :, 8] = rz(np.array([0.0, -sa, ca])) @ R.T
    Jd[:, :, 7] = rz(np.stack([z0, -sp * sa, sp * ca], -1)) @ R.T
    Jd[:, :, 9] = rz(np.stack([-sp, cp * ca, cp * sa], -1)) @ R.T
    if omega is not None:  # d/dlambda of Rz(lambda) v is z x (Rz v); dlambda/dtau = -omega
        zo = np.stack([-o_M[:, 1], o_M[:, 0], z0], -1) @ R.T
        zd = np.stack([-d_M[:, 1], d_M[:, 0], z0], -1) @ R.T
        Jo[:, :, _TAU] = -omega[:, None] * zo
        Jd[:, :, _TAU] = -omega[:, None] * zd
    return o, d, Jo, Jd


def _core_from_params(params: Params, tau_s: float = 0.0) -> tuple[FloatArray, FloatArray]:
    """The core vector (N_CORE,) with w = 0, and R_ref (3, 3), of a Params (rpy is only a format)."""
    T = params.mount.matrix()
    core = np.zeros(N_CORE)
    core[:3] = T[:3, 3]
    core[6:10] = [params.dh.a, params.dh.alpha, params.dh.b, params.dh.beta]
    core[_TAU] = tau_s
    return core, T[:3, :3].copy()


def _params_from_core(core: FloatArray, R_ref: FloatArray) -> Params:
    T = np.eye(4)
    T[:3, :3] = R_ref @ exp_so3(core[3:6])
    T[:3, 3] = core[:3]
    v = np.array(core[6:10], dtype=float)
    v[[1, 3]] = wrap_pi(v[[1, 3]])
    return Params(Pose.from_matrix(T), DH(*map(float, v)))


def _surface_residuals(th: FloatArray, s: PlaneSet, sigma_r: float, R_ref: FloatArray, jac: bool = True,
                       clock: MotorClock | None = None, mount_jac: bool = True
                       ) -> tuple[FloatArray, FloatArray | None]:
    """Range residuals against the ray-plane distance r_p = (d - n.o) / (n.dir), whitened by sigma_r:
    (r - r_p) / sigma_r, shape (K2,), and the dense Jacobian -(dr_p/d[core, nuisance]) / sigma_r,
    (K2, N_CORE + 3P) (lrfcal.model.plane, whose blocks the solver uses without this dense matrix)."""
    rows = plane_rows(th, s, sigma_r, R_ref, jac=jac, clock=clock, mount_jac=mount_jac)
    if rows.Jc is None or rows.Jn is None:
        return rows.res, None
    K2 = s.r.size
    J = np.zeros((K2, N_CORE + 3 * s.n_planes))
    J[:, :N_CORE] = rows.Jc
    J[np.arange(K2)[:, None], N_CORE + 3 * s.plane[:, None] + np.arange(3)] = rows.Jn
    return rows.res, J


@dataclass(frozen=True)
class _Problem:
    """The data of one solve: K returns with their marker centres, optional surface returns, optional clock."""

    lam: FloatArray  # (K,) motor angles at the start clock offset
    mu: FloatArray  # (K,)
    r: FloatArray  # (K,)
    c: FloatArray  # (K, 3) centre of each return's marker in W
    model: str
    radius: float
    sigma_r: float
    surf: _Surf | None = None
    times: FloatArray | None = None  # (K,) laser-clock beam times
    clock: MotorClock | None = None  # set when the clock offset is estimated
    dh_prior: tuple[FloatArray, FloatArray] | None = None  # (mean (4,), sigma (4,)) of a, alpha, b, beta
    mount_jac: bool = True  # False: the mount is held, its Jacobian columns are not computed (left 0)
    divergence: float = 0.0  # full beam divergence [rad]: the footprint on a marker (footprint_depth)

    @property
    def footprint(self) -> FloatArray:
        """(K,) footprint radius at each return's marker, in marker radii (k of :func:`footprint_depth`), from the
        measured range (data, not a function of the unknowns)."""
        return 0.5 * self.divergence * np.maximum(self.r, 0.0) / self.radius

    @property
    def sigma_lat(self) -> FloatArray:
        """(K,) spread of each return's beam axis about its marker's centre, per component: the axis is the point
        hit on the marker's disc (uniform over radius R_m, variance R_m^2 / 4 per component) minus its offset
        within the footprint (uniform over radius k R_m, variance (k R_m)^2 / 4), so R_m sqrt(1 + k^2) / 2."""
        return 0.5 * self.radius * np.sqrt(1.0 + self.footprint ** 2)

    @property
    def n_res(self) -> int:
        """Residual components per return (4 for the sphere: 1 range + 3 lateral, 3 independent)."""
        return 3 if self.model == "paper" else 4

    def subset(self, m: NDArray[np.bool_], ms: NDArray[np.bool_] | None = None) -> _Problem:
        surf = self.surf if self.surf is None or ms is None else self.surf.subset(ms)
        return replace(self, lam=self.lam[m], mu=self.mu[m], r=self.r[m], c=self.c[m], surf=surf,
                       times=None if self.times is None else self.times[m])

    def blocks(self, th: FloatArray, R_ref: FloatArray, jac: bool = True) -> Blocks:
        """All whitened residuals as lrfcal.normal_equations.Blocks: the marker returns and the design drawing's
        prior on the DH parameters (dense rows), the surface returns (plane rows) and the planes' priors."""
        z = np.zeros(0)
        r_d, J_d = z, np.zeros((0, N_CORE))
        if self.r.size:
            res, J = _residuals(th, self, R_ref, jac=jac)
            r_d, J_d = res.ravel(), (None if J is None else J.reshape(-1, N_CORE))
        if self.dh_prior is not None:  # the design drawing's word on the DH parameters
            mean, sig = self.dh_prior
            d = th[6:10] - mean
            d[[1, 3]] = wrap_pi(d[[1, 3]])
            r_d = np.concatenate([r_d, d / sig])
            if J_d is not None:
                Jp = np.zeros((4, N_CORE))
                Jp[:, 6:10] = np.diag(1.0 / sig)
                J_d = np.vstack([J_d, Jp])
        s = self.surf
        if s is None:
            return Blocks(r_d, J_d, z, np.zeros((0, N_CORE)), np.zeros((0, 3)), np.zeros(0, dtype=np.int64), 0)
        rows = plane_rows(th, s, self.sigma_r, R_ref, jac=jac, clock=self.clock, mount_jac=self.mount_jac)
        r_q = w_q = None
        if s.prior_sigma is not None and s.prior_mean is not None:  # the markers' word on the planes
            r_q, w_q = (th[N_CORE:] - s.prior_mean) / s.prior_sigma, 1.0 / s.prior_sigma
        return Blocks(r_d, J_d, rows.res, rows.Jc, rows.Jn, s.plane, s.n_planes, r_q, w_q, s.segments)

    def stacked(self, th: FloatArray, R_ref: FloatArray, jac: bool = True) -> tuple[FloatArray, FloatArray | None]:
        """All whitened residuals as one vector (dense rows, plane rows, plane priors) and the dense Jacobian
        (rows, N_CORE + 3P) (for scipy's robust pass; the normal equations use :meth:`blocks`)."""
        b = self.blocks(th, R_ref, jac)
        res = b.residuals()
        if b.J_dense is None or b.Jc_plane is None or b.Jn_plane is None:
            return res, None
        m, K = b.r_dense.size, b.r_plane.size
        J = np.zeros((res.size, th.size))
        J[:m, :N_CORE] = b.J_dense
        J[m:m + K, :N_CORE] = b.Jc_plane
        J[m + np.arange(K)[:, None], N_CORE + 3 * b.plane[:, None] + np.arange(3)] = b.Jn_plane
        if b.w_prior is not None:
            J[m + K + np.arange(b.w_prior.size), N_CORE + np.arange(b.w_prior.size)] = b.w_prior
        return res, J


def _residuals(th: FloatArray, pb: _Problem, R_ref: FloatArray, jac: bool = True
               ) -> tuple[FloatArray, FloatArray | None]:
    """Whitened residuals (K, n_res) and their Jacobian (K, n_res, N_CORE) (None when jac is False)."""
    lam, omega = _lambda(pb.lam, pb.times, pb.clock, th[_TAU])
    o, d, Jo, Jd = _rays(th[:N_CORE], R_ref, lam, pb.mu, omega, jac=jac)
    r = pb.r - th[_ROFF] - th[_MBIAS]  # the range the scanner would report without its systematic errors
    if pb.model == "paper":
        res = (o + r[:, None] * d - pb.c) / pb.sigma_r
        if Jo is None or Jd is None:
            return res, None
        J = (Jo + r[:, None, None] * Jd) / pb.sigma_r
        J[:, :, _ROFF] = J[:, :, _MBIAS] = -d / pb.sigma_r
        return res, J
    R = pb.radius
    v = pb.c - o
    t = (v * d).sum(1)
    e = v - t[:, None] * d
    rho = np.linalg.norm(e, axis=1)
    s, ds = footprint_depth(rho / R, pb.footprint)
    r_hat = t - R * s
    sig_lat = pb.sigma_lat[:, None]
    res = np.concatenate([((r - r_hat) / pb.sigma_r)[:, None], e / sig_lat], 1)
    if Jo is None or Jd is None:
        return res, None
    Jv = -Jo
    Jt = np.einsum("kij,ki->kj", Jv, d) + np.einsum("ki,kij->kj", v, Jd)
    Je = Jv - d[:, :, None] * Jt[:, None, :] - t[:, None, None] * Jd
    n_e = e / np.maximum(rho, 1e-15)[:, None]
    Jrho = np.einsum("ki,kij->kj", n_e, Je)
    Jrhat = Jt - ds[:, None] * Jrho
    J = np.concatenate([(-Jrhat / pb.sigma_r)[:, None, :], Je / sig_lat[:, :, None]], 1)
    J[:, 0, _ROFF] = J[:, 0, _MBIAS] = -1.0 / pb.sigma_r
    return res, J


def model_residuals(
    params: Params,
    obs: Observations,
    markers_W: ArrayLike,
    *,
    model: str,
    marker_radius_m: float,
    range_sigma_m: float = 0.010,
    beam_divergence_rad: float = 0.0,
) -> tuple[FloatArray, FloatArray]:
    """Whitened residuals (M,) and analytic Jacobian (M, 10) of the returns with a marker (obs.marker >= 0), the
    columns in ESTIMATE_NAMES order (the rotation as a rotation vector in frame M at w = 0).

    M = 3 K (paper) or 4 K (sphere: range residual then the 3 lateral components, per return).
    """
    pb, _ = _problem(obs, markers_W, model, marker_radius_m, range_sigma_m, beam_divergence_rad)
    core, R_ref = _core_from_params(params)
    res, J = _residuals(core, pb, R_ref)
    assert J is not None
    return res.ravel(), J.reshape(-1, N_CORE)[:, :10]


def jacobian_check(
    params: Params,
    obs: Observations,
    markers_W: ArrayLike,
    *,
    model: str,
    marker_radius_m: float,
    range_sigma_m: float = 0.010,
    beam_divergence_rad: float = 0.0,
    step: float = 1e-6,
    clock: MotorClock | None = None,
    rotation_vector: ArrayLike = (0.0, 0.0, 0.0),
) -> FloatArray:
    """Per column, the largest relative difference between the analytic Jacobian and central finite differences:
    the 10 parameters, the clock offset when ``clock`` is given (obs.times_s the beam times), then the range
    offset and the marker range bias (12 or 13 columns), evaluated at the rotation increment ``rotation_vector``
    (to test the right Jacobian away from 0).

    Each column's difference is divided by max(|J_analytic| column max, 1) in whitened units. The clock column
    uses the joint velocity smoothed over ~50 ms, not the slope of the piecewise-linear interpolation, so it
    agrees with finite differences only to the interpolation's curvature error (~1e-3 relative).
    """
    pb, _ = _problem(obs, markers_W, model, marker_radius_m, range_sigma_m, beam_divergence_rad)
    if clock is not None:
        pb = replace(pb, clock=clock)
    th, R_ref = _core_from_params(params)
    th[3:6] = np.asarray(rotation_vector, dtype=float)
    _, J = _residuals(th, pb, R_ref)
    assert J is not None
    J = J.reshape(-1, N_CORE)
    cols = [*range(10), *([_TAU] if clock is not None else []), _ROFF, _MBIAS]
    worst = np.zeros(len(cols))
    for out_j, j in enumerate(cols):
        dp = np.zeros(N_CORE)
        dp[j] = step
        fp = _residuals(th + dp, pb, R_ref, jac=False)[0].ravel()
        fm = _residuals(th - dp, pb, R_ref, jac=False)[0].ravel()
        num = (fp - fm) / (2 * step)
        scale = max(float(np.abs(J[:, j]).max()), 1.0)
        worst[out_j] = float(np.abs(num - J[:, j]).max() / scale)
    return worst


def residuals_3d(
    params: Params, obs: Observations, markers_W: ArrayLike, *, model: str, marker_radius_m: float,
    lambda_rad: ArrayLike | None = None,
) -> FloatArray:
    """3D residual of every return (K, 3), NaN where obs.marker < 0.

    paper: p - c (return point minus marker centre); sphere: (p - c)(1 - R / |p - c|), the return point minus
    the nearest point of the marker's surface (norm = ||p - c| - R|). ``lambda_rad`` (K,) replaces
    obs.lambda_rad (e.g. re-interpolated at an estimated clock offset).
    """
    X = np.asarray(markers_W, dtype=float)
    out = np.full((len(obs), 3), np.nan)
    m = np.asarray(obs.marker) >= 0
    if not m.any():
        return out
    lam = np.asarray(obs.lambda_rad if lambda_rad is None else lambda_rad, dtype=float)
    p = transform_points(params.mount.matrix(), points_M(obs.ranges_m[m], lam[m], obs.mu_rad[m], params.dh))
    diff = p - X[obs.marker[m]]
    if model == "sphere":
        dist = np.linalg.norm(diff, axis=1)
        diff = diff * (1.0 - marker_radius_m / np.maximum(dist, 1e-15))[:, None]
    out[m] = diff
    return out


def _problem(
    obs: Observations, markers_W: ArrayLike, model: str, radius: float, sigma_r: float, divergence: float = 0.0
) -> tuple[_Problem, NDArray[np.bool_]]:
    if model not in MODELS:
        raise InputError(f"solve: model must be one of {', '.join(MODELS)}, got {model!r}")
    X = np.asarray(markers_W, dtype=float)
    if X.ndim != 2 or X.shape[1] != 3:
        raise InputError(f"solve: markers_W must be (n, 3), got {X.shape}")
    if not radius > 0 or not sigma_r > 0:
        raise InputError(f"solve: marker_radius_m and range_sigma_m must be > 0, got {radius}, {sigma_r}")
    if not 0.0 <= divergence < 0.1:
        raise InputError(f"solve: beam_divergence_rad must be in [0, 0.1) rad, got {divergence}")
    marker = np.asarray(obs.marker)
    if np.any(marker >= len(X)):
        raise InputError(f"solve: observation marker index {int(marker.max())} >= number of markers {len(X)}")
    use = (marker >= 0) & np.isfinite(obs.ranges_m) & np.isfinite(obs.lambda_rad) & np.isfinite(obs.mu_rad)
    pb = _Problem(
        np.asarray(obs.lambda_rad, dtype=float)[use], np.asarray(obs.mu_rad, dtype=float)[use],
        np.asarray(obs.ranges_m, dtype=float)[use], X[marker[use]], model, float(radius), float(sigma_r),
        times=np.asarray(obs.times_s, dtype=float)[use], divergence=float(divergence),
    )
    return pb, use


def _fit(th0: FloatArray, R_ref: FloatArray, pb: _Problem, free: NDArray[np.bool_], robust: bool
         ) -> tuple[FloatArray, FloatArray, int, str]:
    """One solver pass over the free unknowns; returns (th with w folded into R_ref, R_ref, nfev, message)."""
    idx = np.flatnonzero(free)

    def full(x: FloatArray) -> FloatArray:
        th = th0.copy()
        th[idx] = x
        return th

    last: list[tuple[FloatArray, FloatArray]] = []  # the Jacobian at the last residuals' point: scipy asks for it

    def fun(x: FloatArray) -> FloatArray:
        res, J = pb.stacked(full(x), R_ref)
        assert J is not None
        last[:] = [(x.copy(), J[:, idx])]
        return res

    def jac(x: FloatArray) -> FloatArray:
        if last and np.array_equal(last[0][0], x):
            return last[0][1]
        J = pb.stacked(full(x), R_ref)[1]
        assert J is not None
        return J[:, idx]

    if robust:
        from scipy.optimize import least_squares  # only here: scipy.optimize takes ~0.2 s to import

        sol = least_squares(fun, th0[idx], jac=jac, method="trf", loss="soft_l1", f_scale=2.0, x_scale="jac",
                            max_nfev=300)
        th, nfev, msg = full(sol.x), int(sol.nfev), str(sol.message)
    else:  # plain least squares on the normal equations (lrfcal.normal_equations)
        # stopped at steps below 1e-2 sigma: the clock offset's Jacobian (smoothed joint velocity) makes the last
        # iterations converge only linearly, by factors of ~2 per evaluation of every marker and surface return
        th, nfev, ok = levenberg_marquardt(th0, lambda x, j: pb.blocks(x, R_ref, j), np.flatnonzero(free[:N_CORE]),
                                           N_CORE, max_iter=100, step_tol=1e-2)
        msg = "converged" if ok else "maximum number of function evaluations exceeded"
    R_new = R_ref @ exp_so3(th[3:6])
    th[3:6] = 0.0
    return th, R_new, nfev, msg


def _inflate_for_correlation(cov: FloatArray, G: FloatArray, JtJ_inv: FloatArray) -> FloatArray:
    """Widen the covariance where errors shared within a scan make it optimistic.

    The cluster-robust (sandwich) covariance (J^T J)^-1 (sum_c g_c g_c^T) (J^T J)^-1, g_c = sum over the rows of
    scan c of J_i r_i (G (clusters, p), lrfcal.normal_equations.cluster_scores), allows any error correlation within
    a scan (the motor angle of a scan comes from the same few quantised encoder readings for all its beams). Each
    parameter's sigma is the larger of the two; the model-based correlations are kept. cov (p, p).
    """
    sandwich = JtJ_inv @ (G.T @ G) @ JtJ_inv
    with np.errstate(over="ignore", divide="ignore", invalid="ignore"):  # a null-variance column stays unscaled
        ratio = np.diag(sandwich) / np.diag(cov)
    scale = np.sqrt(np.maximum(1.0, np.where(np.isfinite(ratio), ratio, 1.0)))
    return cov * np.outer(scale, scale)


def _uncertainty(pb: _Problem, th: FloatArray, R_ref: FloatArray, free: NDArray[np.bool_], n_rows: int,
                 cluster_dense: NDArray[np.int64], cluster_plane: NDArray[np.int64]
                 ) -> tuple[FloatArray, FloatArray, tuple[str, ...], float, str]:
    """The covariance at the solution: s^2 (J^T J)^-1 over the free unknowns, widened for errors shared within a
    scan (``cluster_dense``, ``cluster_plane``: the scan of each dense and plane residual row; each prior row is a
    cluster of its own), with ``n_rows`` independent residuals. J^T J from the normal equations, column-scaled; an
    eigenvalue below RANK_TOL of the largest is rank loss.

    Returns the core covariance (N_CORE, N_CORE) (NaN rows for held unknowns, inf when the information is
    singular), the marginal information over the free core unknowns, their names, the reduced chi-square s^2 and
    the rank in words."""
    b = pb.blocks(th, R_ref)
    core = np.flatnonzero(free[:N_CORE])
    H, _ = assemble(b, core).dense()
    res = b.residuals()
    n_par = H.shape[0]
    s2 = float(res @ res / max(n_rows - n_par, 1))
    col = np.sqrt(np.diag(H))
    col[col == 0] = 1.0
    H_s = H / np.outer(col, col)  # column-scaled: the covariance is computed in these units, then scaled back
    eig = np.linalg.eigvalsh(H_s)
    rank = int(np.sum(eig > eig[-1] * RANK_TOL))  # only numerically null directions count as rank loss
    core_pos = list(range(core.size))
    core_names = tuple(CORE_NAMES[k] for k in core)
    info_scale = 1.0 / max(s2, 1.0)  # the information per unit of the (possibly widened) noise
    if rank < n_par:
        cov = s2 * np.linalg.pinv(H_s, rcond=1e-15) / np.outer(col, col)
        info = _schur(H * info_scale, core_pos)
        rank_txt = f"rank deficient ({rank}/{n_par})"
    else:
        JtJ_inv = np.linalg.inv(H_s) / np.outer(col, col)
        cov = _inflate_for_correlation(s2 * JtJ_inv, cluster_scores(b, core, cluster_dense, cluster_plane), JtJ_inv)
        info = np.linalg.inv(cov[np.ix_(core_pos, core_pos)])
        rank_txt = f"full rank (condition {np.sqrt(eig[-1] / eig[0]):.2e})"
    cov_core = np.full((N_CORE, N_CORE), np.nan)
    cov_core[np.ix_(core, core)] = cov[np.ix_(core_pos, core_pos)]
    if rank < n_par:
        # a covariance from a singular information would be meaningless (and can be 0): none is reported
        cov_core[np.ix_(core, core)] = np.inf
    return cov_core, info, core_names, s2, rank_txt


def _per_return_chi(th: FloatArray, pb: _Problem, R_ref: FloatArray) -> FloatArray:
    """Whitened residual norm per return divided by sqrt(3) (3 independent components for either model)."""
    res, _ = _residuals(th, pb, R_ref, jac=False)
    return np.sqrt((res**2).sum(1) / 3.0)


def solve(
    obs: Observations,
    markers_W: ArrayLike,
    start: Params,
    *,
    model: str,
    marker_radius_m: float,
    range_sigma_m: float = 0.010,
    robust: bool = True,
    surfaces: SurfaceReturns | None = None,
    planes: Sequence[Surface] | None = None,
    clock: MotorClock | None = None,
    clock_offset_s: float = 0.0,
    hold: Sequence[str] = (),
    estimate_range_bias: bool = False,
    beam_divergence_rad: float = 0.0,
) -> Solution:
    """Estimate the 10 parameters (and the clock offset) from marker returns (see the module docstring).

    Args:
        obs: K returns; rows with marker < 0 or non-finite values are ignored. obs.lambda_rad must be the motor
            angles at ``clock_offset_s``; obs.times_s the beam times (laser clock).
        markers_W: (n, 3) marker centres in W (the MDS frame, un-mirrored).
        start: initial parameters (mount pose from the association, DH from the nominal values).
        model: "paper" (eq. (10), return point vs marker centre) or "sphere" (ray vs sphere, sub-beam).
        marker_radius_m: marker sphere radius R_m.
        beam_divergence_rad: the scanner's full beam divergence: the sphere model averages over the footprint
            (:func:`footprint_depth`); 0: the beam's axis alone.
        range_sigma_m: range noise sigma_r (UTM-30LX-EW repeatability, Hokuyo's specification).
        robust: soft-L1 first pass and 4-sigma rejection before the final plain least-squares pass.
        surfaces: optional non-marker returns on the marker-carrying planes (lrfcal.surfaces), solved jointly
            as ray-plane range residuals (whitened by range_sigma_m), rejected at 4 sigma like the markers.
        planes: the lrfcal.surfaces.Surface of each surface index: each plane's normal and offset are nuisance
            parameters with the markers' prior (Surface.prior_sigma); without them the planes are free
            (only flatness counts), started from the returns' normals and offsets.
        clock: the joint states as a MotorClock: the clock offset is then estimated, started at
            ``clock_offset_s``; None holds it at ``clock_offset_s``.
        hold: names from CORE_NAMES held at their start value (not estimated; their sigma is NaN).
        estimate_range_bias: also estimate a constant range offset (every return) and a marker-return range bias
            (the returns of retroreflective markers only; "range walk" of strong returns), started at 0; only
            separable with surface returns (see lrfcal.pipeline).
    Returns:
        Solution: estimate, covariance (10, 10) in ESTIMATE_NAMES order (the rotation as a rotation vector in
        frame M; the marginal over plane nuisances and the clock offset; NaN rows for held parameters), the clock
        offset and its sigma, the marginal information over the estimated core unknowns, residuals_m (K, 3) for
        all K rows (NaN for unused rows), chi (K,) whitened residual per return, residual_rms_m over the returns
        kept, per_marker_rms_m (n,) (NaN for markers without returns).
    Raises:
        CalibrationError: fewer than 4 usable returns or fewer than 3 distinct markers.
    """
    pb_all, use = _problem(obs, markers_W, model, marker_radius_m, range_sigma_m, beam_divergence_rad)
    X = np.asarray(markers_W, dtype=float)
    K = pb_all.r.size
    n_markers = len(np.unique(np.asarray(obs.marker)[use]))
    if K < 4 or n_markers < 3:
        raise CalibrationError(f"solve ({model}): need >= 4 returns on >= 3 markers, got {K} on {n_markers}")
    unknown = sorted(set(hold) - set(CORE_NAMES))
    if unknown:
        raise InputError(f"solve: hold: unknown parameter {unknown[0]!r} (expected one of {', '.join(CORE_NAMES)})")
    th, R_ref = _core_from_params(start, clock_offset_s)
    free_core = np.ones(N_CORE, dtype=bool)
    for name in hold:
        free_core[CORE_NAMES.index(name)] = False
    if clock is None:
        free_core[_TAU] = False
    else:
        pb_all = replace(pb_all, clock=clock)
    if not estimate_range_bias:
        free_core[_ROFF] = free_core[_MBIAS] = False
    if surfaces is not None and len(surfaces):
        surf, nu0 = _surf_problem(surfaces, planes)
        pb_all = replace(pb_all, surf=surf)
        th = np.concatenate([th, nu0])
    free = np.concatenate([free_core, np.ones(th.size - N_CORE, dtype=bool)])
    K2 = 0 if pb_all.surf is None else pb_all.surf.r.size
    nfev = 0
    keep = np.ones(K, dtype=bool)
    keep_s = np.ones(K2, dtype=bool)
    dropped = dropped_s = 0
    changed, msg = True, ""
    if robust:
        if pb_all.surf is None:  # the joint solve starts from the converged marker-only estimate: no soft-L1 pass
            th, R_ref, nf, _ = _fit(th, R_ref, pb_all, free, robust=True)
            nfev += nf
        for _ in range(5):
            chi = _per_return_chi(th, pb_all, R_ref)
            # robust scale of the whitened residuals (median of chi2_3 / 3 is 0.789), never below the model's
            scale = max(1.0, float(np.sqrt(np.median(chi[keep] ** 2) / 0.789)))
            new = chi <= 4.0 * scale
            new_s = keep_s
            if pb_all.surf is not None:
                rs = np.abs(_surface_residuals(th, pb_all.surf, pb_all.sigma_r, R_ref, jac=False,
                                               clock=pb_all.clock)[0])
                new_s = rs <= 4.0 * max(1.0, float(np.median(rs[keep_s]) / 0.674))
            if new.sum() < 4:
                break
            changed = not (np.array_equal(new, keep) and np.array_equal(new_s, keep_s))
            keep, keep_s = new, new_s
            th, R_ref, nf, msg = _fit(th, R_ref, pb_all.subset(keep, keep_s), free, robust=False)
            nfev += nf
            if not changed:  # the last pass was on this very set: it is the solution
                break
        dropped, dropped_s = int(K - keep.sum()), int(K2 - keep_s.sum())
    if not robust or changed:
        th, R_ref, nf, msg = _fit(th, R_ref, pb_all.subset(keep, keep_s), free, robust=False)
        nfev += nf

    pb = pb_all.subset(keep, keep_s)
    k_in = int(keep.sum())
    k_s = int(keep_s.sum())
    n_prior = 0 if pb.surf is None or pb.surf.prior_sigma is None else pb.surf.prior_sigma.size
    scan_s = np.zeros(0, dtype=np.int64) if surfaces is None or pb.surf is None else np.asarray(surfaces.scan)[keep_s]
    # 3 per marker return, 1 per surface return and prior row
    cov_core, info, core_names, s2, rank_txt = _uncertainty(pb, th, R_ref, free, 3 * k_in + k_s + n_prior,
                                                            np.repeat(np.asarray(obs.scan)[use][keep], pb.n_res),
                                                            scan_s)
    params = _params_from_core(th[:N_CORE], R_ref)
    tau = float(th[_TAU])

    lam_all = np.asarray(obs.lambda_rad, dtype=float)
    if pb_all.clock is not None:
        lam_all = pb_all.clock.angles(np.asarray(obs.times_s, dtype=float), tau)[0]
    res3 = residuals_3d(params, obs, X, model=model, marker_radius_m=marker_radius_m, lambda_rad=lam_all)
    idx_used = np.nonzero(use)[0]
    inl = np.zeros(len(obs), dtype=bool)
    inl[idx_used[keep]] = True
    chi_all = np.full(len(obs), np.nan)
    chi_all[idx_used] = _per_return_chi(th, pb_all, R_ref)
    sq = (res3[inl] ** 2).sum(1)
    rms = float(np.sqrt(sq.mean()))
    per = np.full(len(X), np.nan)
    mk = np.asarray(obs.marker)[inl]
    for i in np.unique(mk):
        per[i] = float(np.sqrt(sq[mk == i].mean()))
    surf_txt = f", {k_s}/{K2} surface returns ({dropped_s} dropped)" if K2 else ""
    status = (f"{model}: {msg.rstrip('.')}; {k_in}/{K} returns used ({dropped} dropped > 4 sigma){surf_txt}, "
              f"reduced chi2 {s2:.2f}, {rank_txt}")
    cov10 = cov_core[:10, :10]
    return Solution(
        params=params,
        covariance=cov10,
        sigma=np.sqrt(np.clip(np.diag(cov10), 0.0, None)),
        residual_rms_m=rms,
        residuals_m=res3,
        per_marker_rms_m=per,
        n_observations=k_in,
        n_iterations=nfev,
        status=status,
        clock_offset_s=tau,
        clock_offset_sigma_s=float(np.sqrt(cov_core[_TAU, _TAU])) if free_core[_TAU] else float("nan"),
        information=info,
        information_names=core_names,
        reduced_chi2=s2,
        converged="maximum number of function evaluations" not in msg,
        chi=chi_all,
        inlier=inl,
        lambda_rad=lam_all,
        n_surface_returns=k_s,
        range_offset_m=float(th[_ROFF]),
        range_offset_sigma_m=float(np.sqrt(cov_core[_ROFF, _ROFF])) if free_core[_ROFF] else float("nan"),
        marker_range_bias_m=float(th[_MBIAS]),
        marker_range_bias_sigma_m=float(np.sqrt(cov_core[_MBIAS, _MBIAS])) if free_core[_MBIAS] else float("nan"),
    )


def information_at(
    obs: Observations, markers_W: ArrayLike, params: Params, *, model: str, marker_radius_m: float,
    range_sigma_m: float = 0.010, clock: MotorClock | None = None, clock_offset_s: float = 0.0,
    surfaces: SurfaceReturns | None = None, planes: Sequence[Surface] | None = None, beam_divergence_rad: float = 0.0,
) -> tuple[FloatArray, tuple[str, ...]]:
    """The information J^T J (k, k) of the marker returns at ``params`` (no fit), over the core unknowns that
    would be estimated (the clock offset only when ``clock`` is given; the range offset and marker range bias only
    with ``surfaces``), and their names: what the data can determine, judged before any solver runs.

    With ``surfaces`` (and their ``planes``, as for :func:`solve`), the surface returns' ray-plane range residuals
    and the planes' priors are added, and the planes' nuisance parameters (3 per plane) are marginalised out
    (Schur complement), evaluated at the planes the returns carry (their normals and offsets)."""
    pb, _ = _problem(obs, markers_W, model, marker_radius_m, range_sigma_m, beam_divergence_rad)
    if clock is not None:
        pb = replace(pb, clock=clock)
    th, R_ref = _core_from_params(params, clock_offset_s)
    # the unknowns the calibration estimates: the clock offset when the sweep shows it, the range offset and
    # the marker range bias when surface returns separate them (lrfcal.pipeline's defaults)
    with_surfaces = surfaces is not None and len(surfaces) > 0
    idx = [*range(10), *([_TAU] if clock is not None else []), *([_ROFF, _MBIAS] if with_surfaces else [])]
    names = tuple(CORE_NAMES[i] for i in idx)
    if surfaces is not None and with_surfaces:
        surf, nu0 = _surf_problem(surfaces, planes)
        pb = replace(pb, surf=surf)
        S, _, _ = schur(assemble(pb.blocks(np.concatenate([th, nu0]), R_ref), np.array(idx)))
        return S, names
    _, J = _residuals(th, pb, R_ref)
    assert J is not None
    J = J.reshape(-1, N_CORE)[:, idx]
    return J.T @ J, names


#: the unknowns a targetless calibration never estimates: the world frame is the motor frame M (the planes are
#: free, so the mount is a gauge freedom), and there are no marker returns to carry a marker range bias
_TARGETLESS_HELD = ("x", "y", "z", "rx", "ry", "rz", "marker_range_bias")


def _plane_problem(surfaces: SurfaceReturns, range_sigma_m: float, clock: MotorClock | None,
                   dh_prior: tuple[FloatArray, FloatArray] | None = None) -> tuple[_Problem, FloatArray]:
    """A problem of surface returns only (no marker returns) on free planes, and the planes' nuisance start."""
    if not range_sigma_m > 0:
        raise InputError(f"solve: range_sigma_m must be > 0, got {range_sigma_m}")
    if clock is not None and surfaces.times_s is None:
        raise InputError("solve: the clock offset needs the surface returns' beam times (times_s)")
    surf, nu0 = _surf_problem(surfaces, None)
    z = np.zeros(0)
    pb = _Problem(z, z, z, np.zeros((0, 3)), "sphere", 1.0, float(range_sigma_m), surf=surf,
                  times=z if clock is not None else None, clock=clock, dh_prior=dh_prior, mount_jac=False)
    return pb, nu0


def _plane_free(n_par: int, hold: Sequence[str], clock: MotorClock | None, estimate_range_offset: bool
                ) -> NDArray[np.bool_]:
    unknown = sorted(set(hold) - set(CORE_NAMES))
    if unknown:
        raise InputError(f"solve: hold: unknown parameter {unknown[0]!r} (expected one of {', '.join(CORE_NAMES)})")
    free = np.ones(n_par, dtype=bool)
    for name in (*_TARGETLESS_HELD, *hold):
        free[CORE_NAMES.index(name)] = False
    free[_TAU] &= clock is not None
    free[_ROFF] &= estimate_range_offset
    return free


def solve_planes(
    surfaces: SurfaceReturns,
    start: Params,
    *,
    range_sigma_m: float = 0.010,
    clock: MotorClock | None = None,
    clock_offset_s: float = 0.0,
    hold: Sequence[str] = (),
    estimate_range_offset: bool = False,
    robust: bool = True,
    dh_prior: tuple[FloatArray, FloatArray] | None = None,
) -> Solution:
    """Targetless: the DH parameters (and the clock offset, the range offset) from the flatness of planes alone.

    Every return is a ray-plane range residual (as the surface returns of :func:`solve`) on a plane whose normal and
    offset are free nuisance parameters. The mount is held at ``start.mount`` (without markers the world frame is
    arbitrary: the returns and planes are expressed in the frame of the start's mount, normally M itself).

    Args:
        surfaces: K returns with their plane index (``surface``), the planes' start normals and offsets in the
            start's frame, and beam times (``times_s``, needed with ``clock``).
        start: the start (the mount is held; the DH parameters start from it).
        range_sigma_m: range noise sigma_r.
        clock: the joint states as a MotorClock to estimate the clock offset (started at ``clock_offset_s``); None
            holds it.
        hold: names from CORE_NAMES held at their start value (in addition to the mount).
        estimate_range_offset: also estimate a constant range offset.
        robust: a Huber pass, then plain least squares with returns beyond 4 robust sigma dropped.
        dh_prior: (mean (4,), sigma (4,)) of a, alpha, b, beta: the design drawing's values and tolerance, as
            prior residuals (None: none).
    Returns:
        Solution as :func:`solve` (NaN sigma for held parameters; residuals_m, per_marker_rms_m and chi are empty;
        n_surface_returns the returns kept; inlier (K,) which of the K returns were kept; residual_rms_m the RMS of
        their range residuals).
    Raises:
        CalibrationError: fewer returns than 10 per unknown.
    """
    pb_all, nu0 = _plane_problem(surfaces, range_sigma_m, clock, dh_prior)
    surf = pb_all.surf
    assert surf is not None
    th, R_ref = _core_from_params(start, clock_offset_s)
    th = np.concatenate([th, nu0])
    free = _plane_free(th.size, hold, clock, estimate_range_offset)
    K = surf.r.size
    if 10 * int(free.sum()) > K:
        raise CalibrationError(f"targetless solve: {K} plane returns for {int(free.sum())} unknowns (need 10 each)")
    nfev = 0
    keep = np.ones(K, dtype=bool)
    none = np.zeros(0, dtype=bool)
    msg = "converged"
    if robust:  # Huber first (a plane's stray returns: edges, clutter), then 4-sigma rejection until stable
        th, nfev, msg = _gauss_newton(th, R_ref, pb_all, free, huber=2.0)
    plain = False
    for _ in range(6 if robust else 1):
        if robust:
            rs = np.abs(_surface_residuals(th, surf, pb_all.sigma_r, R_ref, jac=False, clock=clock)[0])
            new = rs <= 4.0 * max(1.0, float(np.median(rs[keep]) / 0.674))
            if plain and np.array_equal(new, keep):
                break
            keep = new
        th, nf, msg = _gauss_newton(th, R_ref, pb_all.subset(none, keep), free)
        nfev += nf
        plain = True
    pb = pb_all.subset(none, keep)
    assert pb.surf is not None
    n_prior = 0 if dh_prior is None else 4
    cov_core, info, core_names, s2, rank_txt = _uncertainty(
        pb, th, R_ref, free, int(keep.sum()) + n_prior,
        -1 - np.arange(n_prior), np.asarray(surfaces.scan)[keep])
    rs = _surface_residuals(th, pb.surf, 1.0, R_ref, jac=False, clock=clock)[0]
    status = (f"planes: {msg.rstrip('.')}; {int(keep.sum())}/{K} plane returns on {surf.n_planes} planes used "
              f"({int(K - keep.sum())} dropped > 4 sigma), reduced chi2 {s2:.2f}, {rank_txt}")
    cov10 = cov_core[:10, :10]

    def sig(i: int) -> float:
        return float(np.sqrt(cov_core[i, i])) if free[i] else float("nan")

    return Solution(
        params=_params_from_core(th[:N_CORE], R_ref), covariance=cov10,
        sigma=np.sqrt(np.clip(np.diag(cov10), 0.0, None)), residual_rms_m=float(np.sqrt(np.mean(rs**2))),
        residuals_m=np.zeros((0, 3)), per_marker_rms_m=np.zeros(0), n_observations=0, n_iterations=nfev,
        status=status, clock_offset_s=float(th[_TAU]), clock_offset_sigma_s=sig(_TAU), information=info,
        information_names=core_names, reduced_chi2=s2, converged=msg == "converged",
        chi=np.zeros(0), inlier=keep, lambda_rad=None, n_surface_returns=int(keep.sum()),
        range_offset_m=float(th[_ROFF]), range_offset_sigma_m=sig(_ROFF),
    )


def _gauss_newton(th0: FloatArray, R_ref: FloatArray, pb: _Problem, free: NDArray[np.bool_],
                  huber: float | None = None, max_iter: int = 60) -> tuple[FloatArray, int, str]:
    """Levenberg-Marquardt on the normal equations (lrfcal.normal_equations: the planes eliminated by the Schur
    complement) over the free unknowns, with Huber weights of threshold ``huber`` (None: plain least squares). The
    mount must be held (R_ref is not updated). Stops when every step is below 1e-3 of its parameter's sigma.
    Returns (th, evaluations, "converged" or why not)."""
    th, n_eval, ok = levenberg_marquardt(th0, lambda x, j: pb.blocks(x, R_ref, j), np.flatnonzero(free[:N_CORE]),
                                         N_CORE, huber=huber, max_iter=max_iter)
    return th, n_eval, "converged" if ok else f"not converged in {max_iter} iterations"


def plane_information(
    surfaces: SurfaceReturns, params: Params, *, range_sigma_m: float = 0.010, clock: MotorClock | None = None,
    clock_offset_s: float = 0.0, hold: Sequence[str] = (), estimate_range_offset: bool = False,
    dh_prior: tuple[FloatArray, FloatArray] | None = None,
) -> tuple[FloatArray, tuple[str, ...]]:
    """The information (k, k) of plane returns at ``params`` (no fit) over the unknowns :func:`solve_planes`
    would estimate, the planes' nuisances marginalised, and their names: what the scene determines, judged
    before any solver runs."""
    pb, nu0 = _plane_problem(surfaces, range_sigma_m, clock, dh_prior)
    th, R_ref = _core_from_params(params, clock_offset_s)
    th = np.concatenate([th, nu0])
    free = _plane_free(th.size, hold, clock, estimate_range_offset)
    core = np.flatnonzero(free[:N_CORE])
    S, _, _ = schur(assemble(pb.blocks(th, R_ref), core))
    return S, tuple(CORE_NAMES[k] for k in core)


def _surf_problem(surfaces: SurfaceReturns, planes: Sequence[Surface] | None) -> tuple[_Surf, FloatArray]:
    """The surface returns as a _Surf with the planes' nuisance start (3P,) (the same set-up as :func:`solve`)."""
    ids, plane_idx = np.unique(surfaces.surface, return_inverse=True)
    first = np.array([np.nonzero(surfaces.surface == p)[0][0] for p in ids])
    n0, t1, t2, nu0 = _plane_nuisance_start(surfaces.normals[first], surfaces.offsets_m[first])
    prior_sigma = None
    if planes is not None:
        t1 = np.array([planes[i].axes[0] for i in ids])
        t2 = np.array([planes[i].axes[1] for i in ids])
        prior_sigma = np.concatenate([planes[i].prior_sigma for i in ids])
    surf = _Surf(surfaces.lambda_rad, surfaces.mu_rad, surfaces.ranges_m, plane_idx.astype(np.int64), n0, t1, t2,
                 nu0.copy(), prior_sigma, times=surfaces.times_s)
    return surf, nu0


def _schur(A: FloatArray, keep: Sequence[int]) -> FloatArray:
    """The information of the ``keep`` block with the others marginalised: A_kk - A_ko A_oo^+ A_ok."""
    keep = list(keep)
    other = [i for i in range(A.shape[0]) if i not in keep]
    if not other:
        return A[np.ix_(keep, keep)]
    Akk, Ako, Aoo = A[np.ix_(keep, keep)], A[np.ix_(keep, other)], A[np.ix_(other, other)]
    return Akk - Ako @ np.linalg.pinv(Aoo, rcond=1e-12) @ Ako.T


__all__ = [
    "CORE_NAMES", "MODELS", "MotorClock", "information_at", "jacobian_check", "model_residuals",
    "plane_information", "residuals_3d", "solve", "solve_planes", "sphere_depth", "wrap_pi",
]
