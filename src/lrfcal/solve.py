"""Stage 6: Levenberg-Marquardt over the 10 parameters theta = (x, y, z, roll, pitch, yaw, a, alpha, b, beta).

Forward model (kinematics.py, eq. (3)), per return k with motor angle lambda_k, bearing mu_k, range r_k and
phi_k = beta + mu_k:

    o_M = Rz(lambda) [a, -b sin(alpha), b cos(alpha)]              beam origin in M
    d_M = Rz(lambda) [cos(phi), sin(phi) cos(alpha), sin(phi) sin(alpha)]   unit direction in M
    o = R o_M + t,  d = R d_M,  R = Rz(yaw) Ry(pitch) Rx(roll),  t = (x, y, z)     in W

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

Analytic Jacobian (chain rule; dX/dtheta_j written X_j):
    translation: o_j = e_j, d_j = 0;   mount angle q: o_j = (dR/dq) o_M, d_j = (dR/dq) d_M;
    DH parameter p: o_j = R Rz(lambda) d(o_loc)/dp, d_j = R Rz(lambda) d(d_loc)/dp with
      d o_loc/da = (1,0,0), d o_loc/dalpha = (0, -b ca, -b sa), d o_loc/db = (0, -sa, ca), d o_loc/dbeta = 0,
      d d_loc/dalpha = (0, -sphi sa, sphi ca), d d_loc/dbeta = (-sphi, cphi ca, cphi sa), others 0.
    paper: (o + r d)_j / sigma_r.
    sphere: v_j = -o_j; t_j = v_j.d + v.d_j; e_j = v_j - t_j d - t d_j; |e|_j = (e/|e|).e_j;
      r_hat_j = t_j - s'(u) |e|_j;  range residual_j = -r_hat_j / sigma_r;  lateral_j = e_j / sigma_lat.

Solver: a robust pass (trf, soft-L1 loss) from the start, then plain least squares with observations whose
whitened residual exceeds 4 sigma dropped (repeated until the inlier set is stable), whose Jacobian gives the
covariance s^2 (J^T J)^-1, s^2 the reduced chi-square of the whitened residuals.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.optimize import least_squares
from scipy.special import expit

from .errors import CalibrationError, InputError
from .kinematics import PARAM_NAMES, Params
from .surfaces import Surface, SurfaceReturns
from .types import Observations, Solution

FloatArray = NDArray[np.float64]

MODELS = ("paper", "sphere")
_ETA = 0.05  # softness of the sphere's rim in s(u)
_ANGLE_IDX = (3, 4, 5, 7, 9)  # roll, pitch, yaw, alpha, beta


def wrap_pi(a: ArrayLike) -> FloatArray:
    """Wrap angles to (-pi, pi]."""
    a = np.asarray(a, dtype=float)
    return a - 2 * np.pi * np.ceil((a - np.pi) / (2 * np.pi))


def sphere_depth(u: ArrayLike, eta: float = _ETA) -> tuple[FloatArray, FloatArray]:
    """Smoothed depth of a unit sphere's surface below its centre plane at lateral offset u, and ds/du.

    s(u) = sqrt(eta log(1 + exp((1 - u^2) / eta))) ~ sqrt(1 - u^2) inside, -> 0 beyond the rim;
    ds/du = -u expit((1 - u^2) / eta) / s (bounded; |ds/du| <= ~1 / sqrt(eta log 2) near u = 1).
    """
    u = np.asarray(u, dtype=float)
    q = (1.0 - u * u) / eta
    far = q < -30.0  # beyond the rim: softplus(q) = exp(q) to double precision, written to avoid 0 / 0
    qn = np.where(far, 0.0, q)
    s_near = np.sqrt(eta * np.logaddexp(0.0, qn))
    s = np.where(far, np.sqrt(eta) * np.exp(0.5 * q), s_near)
    ds = np.where(far, -u * np.exp(0.5 * q) / np.sqrt(eta), -u * expit(qn) / s_near)
    return s, ds


def _rot(axis: str, t: float) -> tuple[FloatArray, FloatArray]:
    """Rotation matrix about an axis and its derivative with respect to the angle."""
    c, s = np.cos(t), np.sin(t)
    if axis == "x":
        return np.array([[1, 0, 0], [0, c, -s], [0, s, c]]), np.array([[0, 0, 0], [0, -s, -c], [0, c, -s]])
    if axis == "y":
        return np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]]), np.array([[-s, 0, c], [0, 0, 0], [-c, 0, -s]])
    return np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]]), np.array([[-s, -c, 0], [c, -s, 0], [0, 0, 0]])


def _rz_apply(cl: FloatArray, sl: FloatArray, v: FloatArray) -> FloatArray:
    """Rz(lambda_k) v_k for (K,) cos/sin and v (K, 3) or (3,)."""
    v = np.broadcast_to(v, (cl.size, 3))
    return np.stack([cl * v[:, 0] - sl * v[:, 1], sl * v[:, 0] + cl * v[:, 1], v[:, 2]], -1)


def beam_rays_W(
    theta: ArrayLike, lambda_rad: ArrayLike, mu_rad: ArrayLike, jac: bool = True
) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray]:
    """Beam origins and unit directions in W and their Jacobians with respect to theta.

    Args:
        theta: (10,) parameters in PARAM_NAMES order.
        lambda_rad, mu_rad: (K,) motor angles and beam bearings.
    Returns:
        o (K, 3), d (K, 3), do/dtheta (K, 3, 10), dd/dtheta (K, 3, 10) (the last two empty (0, 3, 10) when
        ``jac`` is False).
    """
    th = np.asarray(theta, dtype=float).reshape(10)
    x, y, z, roll, pitch, yaw, a, al, b, be = th
    lam = np.atleast_1d(np.asarray(lambda_rad, dtype=float))
    phi = be + np.atleast_1d(np.asarray(mu_rad, dtype=float))
    lam, phi = np.broadcast_arrays(lam, phi)
    K = lam.size
    cl, sl = np.cos(lam), np.sin(lam)
    ca, sa = np.cos(al), np.sin(al)
    cp, sp = np.cos(phi), np.sin(phi)
    Rx, dRx = _rot("x", roll)
    Ry, dRy = _rot("y", pitch)
    Rz, dRz = _rot("z", yaw)
    R = Rz @ Ry @ Rx
    dR = (Rz @ Ry @ dRx, Rz @ dRy @ Rx, dRz @ Ry @ Rx)

    o_M = _rz_apply(cl, sl, np.array([a, -b * sa, b * ca]))
    d_loc = np.stack([cp, sp * ca, sp * sa], -1)
    d_M = _rz_apply(cl, sl, d_loc)
    o = o_M @ R.T + np.array([x, y, z])
    d = d_M @ R.T
    if not jac:
        empty = np.zeros((0, 3, 10))
        return o, d, empty, empty

    Jo = np.zeros((K, 3, 10))
    Jd = np.zeros((K, 3, 10))
    Jo[:, 0, 0] = Jo[:, 1, 1] = Jo[:, 2, 2] = 1.0
    for j, D in enumerate(dR):
        Jo[:, :, 3 + j] = o_M @ D.T
        Jd[:, :, 3 + j] = d_M @ D.T
    z0 = np.zeros(K)
    Jo[:, :, 6] = _rz_apply(cl, sl, np.array([1.0, 0.0, 0.0])) @ R.T
    Jo[:, :, 7] = _rz_apply(cl, sl, np.array([0.0, -b * ca, -b * sa])) @ R.T
    Jo[:, :, 8] = _rz_apply(cl, sl, np.array([0.0, -sa, ca])) @ R.T
    Jd[:, :, 7] = _rz_apply(cl, sl, np.stack([z0, -sp * sa, sp * ca], -1)) @ R.T
    Jd[:, :, 9] = _rz_apply(cl, sl, np.stack([-sp, cp * ca, cp * sa], -1)) @ R.T
    return o, d, Jo, Jd


@dataclass(frozen=True)
class _Surf:
    """Non-marker returns (K2 rows) on P planes whose normals and offsets are nuisance parameters.

    Plane j: n_j = m_j / |m_j|, m_j = n0_j + u1_j t1_j + u2_j t2_j (t1, t2 tangent to the initial normal n0),
    n_j . p = d_j. The nuisance vector follows the 10 parameters: (u1, u2, d) per plane.
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

    def subset(self, m: NDArray[np.bool_]) -> _Surf:
        return _Surf(self.lam[m], self.mu[m], self.r[m], self.plane[m], self.n0, self.t1, self.t2,
                     self.prior_mean, self.prior_sigma)

    @property
    def n_planes(self) -> int:
        return int(self.n0.shape[0])


def _plane_nuisance_start(normals: FloatArray, offsets: FloatArray) -> tuple[FloatArray, FloatArray, FloatArray,
                                                                             FloatArray]:
    """Tangent bases t1, t2 (P, 3) of initial normals (P, 3) and the start nuisance vector (3P,)."""
    n0 = np.asarray(normals, dtype=float).reshape(-1, 3)
    helper = np.where(np.abs(n0[:, :1]) < 0.9, [[1.0, 0.0, 0.0]], [[0.0, 1.0, 0.0]])
    t1 = np.cross(n0, helper)
    t1 /= np.linalg.norm(t1, axis=1, keepdims=True)
    t2 = np.cross(n0, t1)
    nu0 = np.column_stack([np.zeros(len(n0)), np.zeros(len(n0)), np.asarray(offsets, dtype=float)]).ravel()
    return n0, t1, t2, nu0


def _surface_residuals(th: FloatArray, s: _Surf, sigma_r: float, jac: bool = True
                       ) -> tuple[FloatArray, FloatArray | None]:
    """Range residuals against the ray-plane distance r_p = (d - n.o) / (n.dir), whitened by sigma_r:
    (r - r_p) / sigma_r, shape (K2,), and the Jacobian -(dr_p/d[theta, nuisance]) / sigma_r, (K2, 10 + 3P):
        dr_p/dtheta = -(n.do + r_p n.ddir) / (n.dir),   dr_p/dd = 1 / (n.dir),
        dr_p/dn = -(o + r_p dir) / (n.dir),   dn/du_i = (t_i - n (n.t_i)) / |m|.
    """
    P = s.n_planes
    nu = th[10:].reshape(P, 3)
    m = s.n0 + nu[:, :1] * s.t1 + nu[:, 1:2] * s.t2
    m_norm = np.linalg.norm(m, axis=1, keepdims=True)
    n_p = m / m_norm
    o, d, Jo, Jd = beam_rays_W(th[:10], s.lam, s.mu, jac=jac)
    n = n_p[s.plane]
    nd = (n * d).sum(1)
    rp = (nu[s.plane, 2] - (n * o).sum(1)) / nd
    res = (s.r - rp) / sigma_r
    if not jac:
        return res, None
    K2 = s.r.size
    J = np.zeros((K2, 10 + 3 * P))
    J[:, :10] = -(np.einsum("ki,kij->kj", n, Jo) + rp[:, None] * np.einsum("ki,kij->kj", n, Jd)) / nd[:, None]
    drp_dn = -(o + rp[:, None] * d) / nd[:, None]
    rows = np.arange(K2)
    for i, t in enumerate((s.t1, s.t2)):
        dn_du = (t - n_p * (n_p * t).sum(1, keepdims=True)) / m_norm  # (P, 3)
        J[rows, 10 + 3 * s.plane + i] = (drp_dn * dn_du[s.plane]).sum(1)
    J[rows, 10 + 3 * s.plane + 2] = 1.0 / nd
    return res, -J / sigma_r


@dataclass(frozen=True)
class _Problem:
    """The data of one solve: K returns with their marker centres."""

    lam: FloatArray  # (K,)
    mu: FloatArray  # (K,)
    r: FloatArray  # (K,)
    c: FloatArray  # (K, 3) centre of each return's marker in W
    model: str
    radius: float
    sigma_r: float
    surf: _Surf | None = None

    @property
    def sigma_lat(self) -> float:
        return 0.5 * self.radius

    @property
    def n_res(self) -> int:
        """Residual components per return (4 for the sphere: 1 range + 3 lateral, 3 independent)."""
        return 3 if self.model == "paper" else 4

    def subset(self, m: NDArray[np.bool_], ms: NDArray[np.bool_] | None = None) -> _Problem:
        surf = self.surf if self.surf is None or ms is None else self.surf.subset(ms)
        return _Problem(self.lam[m], self.mu[m], self.r[m], self.c[m], self.model, self.radius, self.sigma_r, surf)

    def stacked(self, th: FloatArray, jac: bool = True) -> tuple[FloatArray, FloatArray | None]:
        """All whitened residuals as one vector (markers, then surfaces) and the (rows, 10) Jacobian."""
        res, J = _residuals(th, self, jac=jac)
        res_v, J_m = res.ravel(), None if J is None else J.reshape(-1, 10)
        if self.surf is None:
            return res_v, J_m
        rs, Js = _surface_residuals(th, self.surf, self.sigma_r, jac=jac)
        n_par = th.size
        rp, Jp = np.zeros(0), np.zeros((0, n_par))
        if self.surf.prior_sigma is not None and self.surf.prior_mean is not None:  # the markers' word on the planes
            rp = (th[10:] - self.surf.prior_mean) / self.surf.prior_sigma
            Jp = np.zeros((rp.size, n_par))
            Jp[:, 10:] = np.diag(1.0 / self.surf.prior_sigma)
        if J_m is None or Js is None:
            return np.concatenate([res_v, rs, rp]), None
        J_m = np.hstack([J_m, np.zeros((J_m.shape[0], n_par - 10))])
        return np.concatenate([res_v, rs, rp]), np.vstack([J_m, Js, Jp])


def _residuals(th: FloatArray, pb: _Problem, jac: bool = True) -> tuple[FloatArray, FloatArray | None]:
    """Whitened residuals (K, n_res) and their Jacobian (K, n_res, 10) (None when jac is False)."""
    o, d, Jo, Jd = beam_rays_W(th[:10], pb.lam, pb.mu, jac=jac)
    if pb.model == "paper":
        res = (o + pb.r[:, None] * d - pb.c) / pb.sigma_r
        J = (Jo + pb.r[:, None, None] * Jd) / pb.sigma_r if jac else None
        return res, J
    R = pb.radius
    v = pb.c - o
    t = (v * d).sum(1)
    e = v - t[:, None] * d
    rho = np.linalg.norm(e, axis=1)
    s, ds = sphere_depth(rho / R)
    r_hat = t - R * s
    res = np.concatenate([((pb.r - r_hat) / pb.sigma_r)[:, None], e / pb.sigma_lat], 1)
    if not jac:
        return res, None
    Jv = -Jo
    Jt = np.einsum("kij,ki->kj", Jv, d) + np.einsum("ki,kij->kj", v, Jd)
    Je = Jv - d[:, :, None] * Jt[:, None, :] - t[:, None, None] * Jd
    n_e = e / np.maximum(rho, 1e-15)[:, None]
    Jrho = np.einsum("ki,kij->kj", n_e, Je)
    Jrhat = Jt - ds[:, None] * Jrho
    J = np.concatenate([(-Jrhat / pb.sigma_r)[:, None, :], Je / pb.sigma_lat], 1)
    return res, J


def model_residuals(
    params: Params | ArrayLike,
    obs: Observations,
    markers_W: ArrayLike,
    *,
    model: str,
    marker_radius_m: float,
    range_sigma_m: float = 0.010,
) -> tuple[FloatArray, FloatArray]:
    """Whitened residuals (M,) and analytic Jacobian (M, 10) of the returns with a marker (obs.marker >= 0).

    M = 3 K (paper) or 4 K (sphere: range residual then the 3 lateral components, per return).
    """
    pb, _ = _problem(obs, markers_W, model, marker_radius_m, range_sigma_m)
    th = params.vector() if isinstance(params, Params) else np.asarray(params, dtype=float)
    res, J = _residuals(th, pb)
    assert J is not None
    return res.ravel(), J.reshape(-1, 10)


def jacobian_check(
    params: Params | ArrayLike,
    obs: Observations,
    markers_W: ArrayLike,
    *,
    model: str,
    marker_radius_m: float,
    range_sigma_m: float = 0.010,
    step: float = 1e-6,
) -> float:
    """Largest relative difference between the analytic Jacobian and central finite differences.

    The difference of each column is divided by max(|J_analytic| column max, 1) in whitened units.
    """
    pb, _ = _problem(obs, markers_W, model, marker_radius_m, range_sigma_m)
    th = params.vector() if isinstance(params, Params) else np.asarray(params, dtype=float)
    _, J = _residuals(th, pb)
    assert J is not None
    J = J.reshape(-1, 10)
    worst = 0.0
    for j in range(10):
        dp = np.zeros(10)
        dp[j] = step
        fp = _residuals(th + dp, pb, jac=False)[0].ravel()
        fm = _residuals(th - dp, pb, jac=False)[0].ravel()
        num = (fp - fm) / (2 * step)
        scale = max(float(np.abs(J[:, j]).max()), 1.0)
        worst = max(worst, float(np.abs(num - J[:, j]).max() / scale))
    return worst


def residuals_3d(
    params: Params, obs: Observations, markers_W: ArrayLike, *, model: str, marker_radius_m: float
) -> FloatArray:
    """3D residual of every return (K, 3), NaN where obs.marker < 0.

    paper: p - c (return point minus marker centre); sphere: (p - c)(1 - R / |p - c|), the return point minus
    the nearest point of the marker's surface (norm = ||p - c| - R|).
    """
    X = np.asarray(markers_W, dtype=float)
    out = np.full((len(obs), 3), np.nan)
    m = np.asarray(obs.marker) >= 0
    if not m.any():
        return out
    from .kinematics import points_W

    p = points_W(obs.ranges_m[m], obs.lambda_rad[m], obs.mu_rad[m], params)
    diff = p - X[obs.marker[m]]
    if model == "sphere":
        dist = np.linalg.norm(diff, axis=1)
        diff = diff * (1.0 - marker_radius_m / np.maximum(dist, 1e-15))[:, None]
    out[m] = diff
    return out


def _problem(
    obs: Observations, markers_W: ArrayLike, model: str, radius: float, sigma_r: float
) -> tuple[_Problem, NDArray[np.bool_]]:
    if model not in MODELS:
        raise InputError(f"solve: model must be one of {', '.join(MODELS)}, got {model!r}")
    X = np.asarray(markers_W, dtype=float)
    if X.ndim != 2 or X.shape[1] != 3:
        raise InputError(f"solve: markers_W must be (n, 3), got {X.shape}")
    if not radius > 0 or not sigma_r > 0:
        raise InputError(f"solve: marker_radius_m and range_sigma_m must be > 0, got {radius}, {sigma_r}")
    marker = np.asarray(obs.marker)
    if np.any(marker >= len(X)):
        raise InputError(f"solve: observation marker index {int(marker.max())} >= number of markers {len(X)}")
    use = (marker >= 0) & np.isfinite(obs.ranges_m) & np.isfinite(obs.lambda_rad) & np.isfinite(obs.mu_rad)
    pb = _Problem(
        np.asarray(obs.lambda_rad, dtype=float)[use], np.asarray(obs.mu_rad, dtype=float)[use],
        np.asarray(obs.ranges_m, dtype=float)[use], X[marker[use]], model, float(radius), float(sigma_r),
    )
    return pb, use


def _fit(th0: FloatArray, pb: _Problem, robust: bool) -> tuple[FloatArray, int, str]:
    def fun(th: FloatArray) -> FloatArray:
        return pb.stacked(th, jac=False)[0]

    def jac(th: FloatArray) -> FloatArray:
        J = pb.stacked(th)[1]
        assert J is not None
        return J

    if robust:
        sol = least_squares(fun, th0, jac=jac, method="trf", loss="soft_l1", f_scale=2.0, x_scale="jac",
                            max_nfev=200)
    else:
        method = "lm" if pb.r.size * pb.n_res >= 10 else "trf"
        sol = least_squares(fun, th0, jac=jac, method=method, x_scale="jac", xtol=1e-12, ftol=1e-12,
                            gtol=1e-12, max_nfev=400)
    return sol.x, int(sol.nfev), str(sol.message)


def _inflate_for_correlation(cov: FloatArray, J: FloatArray, res: FloatArray, cluster: NDArray[np.int64],
                             JtJ_inv: FloatArray) -> FloatArray:
    """Widen the covariance where errors shared within a scan make it optimistic.

    The cluster-robust (sandwich) covariance (J^T J)^-1 (sum_c g_c g_c^T) (J^T J)^-1, g_c = sum over the rows of
    scan c of J_i r_i, allows any error correlation within a scan (the motor angle of a scan comes from the same
    few quantised encoder readings for all its beams). Each parameter's sigma is the larger of the two; the
    model-based correlations are kept. cov (p, p), J (m, p), res (m,), cluster (m,) ids.
    """
    _, inverse = np.unique(cluster, return_inverse=True)
    G = np.zeros((int(inverse.max()) + 1, J.shape[1]))
    np.add.at(G, inverse, J * res[:, None])
    sandwich = JtJ_inv @ (G.T @ G) @ JtJ_inv
    scale = np.sqrt(np.maximum(1.0, np.diag(sandwich) / np.maximum(np.diag(cov), 1e-300)))
    return cov * np.outer(scale, scale)


def _per_return_chi(th: FloatArray, pb: _Problem) -> FloatArray:
    """Whitened residual norm per return divided by sqrt(3) (3 independent components for either model)."""
    res, _ = _residuals(th, pb, jac=False)
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
) -> Solution:
    """Estimate the 10 parameters from marker returns (see the module docstring for the models).

    Args:
        obs: K returns; rows with marker < 0 or non-finite values are ignored.
        markers_W: (n, 3) marker centres in W (the MDS frame, un-mirrored).
        start: initial parameters (mount pose from the association, DH from the nominal values).
        model: "paper" (eq. (10), return point vs marker centre) or "sphere" (ray vs sphere, sub-beam).
        marker_radius_m: marker sphere radius R_m.
        range_sigma_m: range noise sigma_r (UTM-30LX-EW repeatability, its spec sheet).
        robust: soft-L1 first pass and 4-sigma rejection before the final plain least-squares pass.
        surfaces: optional non-marker returns on the marker-carrying planes (lrfcal.surfaces), solved jointly
            as ray-plane range residuals (whitened by range_sigma_m), rejected at 4 sigma like the markers.
        planes: the lrfcal.surfaces.Surface of each surface index: each plane's normal and offset are nuisance
            parameters with the markers' prior (Surface.prior_sigma); without them the planes are free
            (only flatness counts), started from the returns' normals and offsets.
    Returns:
        Solution with angles wrapped to (-pi, pi], covariance s^2 (J^T J)^-1 (pseudo-inverse, and status says
        "rank deficient" when J^T J is singular), residuals_m (K, 3) for all K rows (NaN for unused rows),
        residual_rms_m over the returns kept, per_marker_rms_m (n,) (NaN for markers without returns).
    Raises:
        CalibrationError: fewer than 4 usable returns or fewer than 3 distinct markers.
    """
    pb_all, use = _problem(obs, markers_W, model, marker_radius_m, range_sigma_m)
    X = np.asarray(markers_W, dtype=float)
    K = pb_all.r.size
    n_markers = len(np.unique(np.asarray(obs.marker)[use]))
    if K < 4 or n_markers < 3:
        raise CalibrationError(f"solve ({model}): need >= 4 returns on >= 3 markers, got {K} on {n_markers}")
    th = start.vector().astype(float)
    if surfaces is not None and len(surfaces):
        ids, plane_idx = np.unique(surfaces.surface, return_inverse=True)
        first = np.array([np.nonzero(surfaces.surface == p)[0][0] for p in ids])
        n0, t1, t2, nu0 = _plane_nuisance_start(surfaces.normals[first], surfaces.offsets_m[first])
        prior_sigma = None
        if planes is not None:
            t1 = np.array([planes[i].axes[0] for i in ids])
            t2 = np.array([planes[i].axes[1] for i in ids])
            prior_sigma = np.concatenate([planes[i].prior_sigma for i in ids])
        surf = _Surf(surfaces.lambda_rad, surfaces.mu_rad, surfaces.ranges_m, plane_idx.astype(np.int64), n0, t1, t2,
                     nu0.copy(), prior_sigma)
        pb_all = _Problem(pb_all.lam, pb_all.mu, pb_all.r, pb_all.c, pb_all.model, pb_all.radius, pb_all.sigma_r,
                          surf)
        th = np.concatenate([th, nu0])
    K2 = 0 if pb_all.surf is None else pb_all.surf.r.size
    n_par = th.size
    nfev = 0
    keep = np.ones(K, dtype=bool)
    keep_s = np.ones(K2, dtype=bool)
    dropped = dropped_s = 0
    if robust:
        if pb_all.surf is None:  # the joint solve starts from the converged marker-only estimate: no soft-L1 pass
            th, nf, _ = _fit(th, pb_all, robust=True)
            nfev += nf
        for _ in range(5):
            chi = _per_return_chi(th, pb_all)
            # robust scale of the whitened residuals (median of chi2_3 / 3 is 0.789), never below the model's
            scale = max(1.0, float(np.sqrt(np.median(chi[keep] ** 2) / 0.789)))
            new = chi <= 4.0 * scale
            new_s = keep_s
            if pb_all.surf is not None:
                rs = np.abs(_surface_residuals(th, pb_all.surf, pb_all.sigma_r, jac=False)[0])
                new_s = rs <= 4.0 * max(1.0, float(np.median(rs[keep_s]) / 0.674))
            if new.sum() < 4:
                break
            changed = not (np.array_equal(new, keep) and np.array_equal(new_s, keep_s))
            keep, keep_s = new, new_s
            th, nf, msg = _fit(th, pb_all.subset(keep, keep_s), robust=False)
            nfev += nf
            if not changed:
                break
        dropped, dropped_s = int(K - keep.sum()), int(K2 - keep_s.sum())
    th, nf, msg = _fit(th, pb_all.subset(keep, keep_s), robust=False)
    nfev += nf

    pb = pb_all.subset(keep, keep_s)
    res, J = pb.stacked(th)
    assert J is not None
    k_in = int(keep.sum())
    k_s = int(keep_s.sum())
    n_prior = 0 if pb.surf is None or pb.surf.prior_sigma is None else pb.surf.prior_sigma.size
    dof = max(3 * k_in + k_s + n_prior - n_par, 1)  # 3 per marker return, 1 per surface return and prior row
    s2 = float(res @ res / dof)
    col = np.linalg.norm(J, axis=0)
    col[col == 0] = 1.0
    sv = np.linalg.svd(J / col, compute_uv=False)
    rank = int(np.sum(sv > sv[0] * 1e-9))
    JtJ = J.T @ J
    if rank < n_par:
        cov = s2 * np.linalg.pinv(JtJ, rcond=1e-12)
        _, _, Vt = np.linalg.svd(J / col)
        worst = Vt[-1] / col
        names = [PARAM_NAMES[i] if i < 10 else f"plane{(i - 10) // 3}" for i in np.argsort(-np.abs(worst))[:3]]
        rank_txt = f"rank deficient ({rank}/{n_par}), unobservable direction mostly {'/'.join(names)}"
    else:
        cov = s2 * np.linalg.inv(JtJ)
        clusters = [np.repeat(np.asarray(obs.scan)[use][keep], pb.n_res)]
        if pb.surf is not None and surfaces is not None:
            clusters += [np.asarray(surfaces.scan)[keep_s], -1 - np.arange(n_prior)]
        cov = _inflate_for_correlation(cov, J, res, np.concatenate(clusters), np.linalg.inv(JtJ))
        rank_txt = f"full rank (condition {sv[0] / sv[-1]:.2e})"
    cov = cov[:10, :10]  # marginal covariance of the 10 parameters (plane nuisances integrated out)
    th = th[:10]
    th[list(_ANGLE_IDX)] = wrap_pi(th[list(_ANGLE_IDX)])
    params = Params.from_vector(th)

    res3 = residuals_3d(params, obs, X, model=model, marker_radius_m=marker_radius_m)
    idx_used = np.nonzero(use)[0]
    inl = np.zeros(len(obs), dtype=bool)
    inl[idx_used[keep]] = True
    sq = (res3[inl] ** 2).sum(1)
    rms = float(np.sqrt(sq.mean()))
    per = np.full(len(X), np.nan)
    mk = np.asarray(obs.marker)[inl]
    for i in np.unique(mk):
        per[i] = float(np.sqrt(sq[mk == i].mean()))
    surf_txt = f", {k_s}/{K2} surface returns ({dropped_s} dropped)" if K2 else ""
    status = (f"{model}: {msg.rstrip('.')}; {k_in}/{K} returns used ({dropped} dropped > 4 sigma){surf_txt}, "
              f"reduced chi2 {s2:.3g}, {rank_txt}")
    return Solution(
        params=params,
        covariance=cov,
        sigma=np.sqrt(np.clip(np.diag(cov), 0.0, None)),
        residual_rms_m=rms,
        residuals_m=res3,
        per_marker_rms_m=per,
        n_observations=k_in,
        n_iterations=nfev,
        status=status,
    )


__all__ = [
    "MODELS", "beam_rays_W", "jacobian_check", "model_residuals", "residuals_3d", "solve", "sphere_depth",
    "wrap_pi",
]
