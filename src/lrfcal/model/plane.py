"""Ray-plane range residuals and their Jacobian, row by row without (K, 3, N_CORE) temporaries.

A return k on plane j (lrfcal.model.unknowns.PlaneSet) has the residual (r_k - range_scale r_p - range_offset) /
sigma_r (lrfcal.model.scanner.reported_range) against the ray-plane distance r_p = (d_j - n_j . o) / (n_j . dir)
(lrfcal.estimate.solve's module docstring has the forward model).
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

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from lrfcal.model.kinematics import exp_so3, right_jacobian_so3
from lrfcal.model.motor import MotorClock, motor_angles
from lrfcal.model.scanner import reported_range, true_bearing
from lrfcal.model.unknowns import BSCALE, N_CORE, SCALE, PlaneSet

FloatArray = NDArray[np.float64]


@dataclass(frozen=True)
class PlaneRows:
    """Whitened residuals res (K,) of plane returns and, with the Jacobian, its core block Jc (K, N_CORE) and each
    row's own plane's nuisance block Jn (K, 3) (columns N_CORE + 3 plane + (0, 1, 2) of the full Jacobian)."""

    res: FloatArray
    Jc: FloatArray | None = None
    Jn: FloatArray | None = None


def plane_rows(th: FloatArray, s: PlaneSet, sigma_r: float, R_ref: FloatArray, *, jac: bool = True,
               clock: MotorClock | None = None, mount_jac: bool = True, chart: FloatArray | None = None
               ) -> PlaneRows:
    """The plane returns' whitened residuals and Jacobian blocks at th (N_CORE + 3P,) (module docstring).

    ``clock``: the clock offset is an unknown (its column is 0 otherwise); ``mount_jac`` False leaves the mount's
    columns 0 (a held mount); ``chart`` (6, 4): what the scan-plane columns are derivatives by (None: the DH
    parameters). Per-plane quantities are gathered to the rows as scalars (K,), and the Jacobian blocks
    are column-major: both keep the work a few passes over (K,) arrays."""
    P = s.n_planes
    nu = th[N_CORE:].reshape(P, 3)
    m = s.n0 + nu[:, :1] * s.t1 + nu[:, 1:2] * s.t2
    m_norm = np.linalg.norm(m, axis=1, keepdims=True)
    n_p = m / m_norm  # (P, 3) in W
    motor = motor_angles(th, s.lam, s.times, clock)
    lam = motor.lam
    t = th[:3]
    a, al, b, be = th[6:10]
    R = R_ref @ exp_so3(th[3:6])
    ca, sa = np.cos(al), np.sin(al)
    bearing = true_bearing(th, s.mu)
    cp, sp = _cos_sin_sum(be, bearing.mu, s.trig_mu, th[BSCALE] == 1.0)  # phi = beta + mu_true
    cl, sl = _cos_sin_sum(0.0, lam, s.trig_lam, clock is None and th[SCALE] == 1.0)
    pl = s.plane
    nM = n_p @ R  # (P, 3): R^T n per plane
    gx, gy = nM[:, 0][pl], nM[:, 1][pl]
    nx, ny, nz = cl * gx + sl * gy, cl * gy - sl * gx, nM[:, 2][pl]  # n_0 = Rz(-lambda) R^T n
    oy, oz = -b * sa, b * ca  # o_0 = (a, oy, oz)
    dy, dz = sp * ca, sp * sa  # dir_0 = (cp, dy, dz)
    nd = nx * cp + ny * dy + nz * dz
    rp = ((nu[:, 2] - n_p @ t)[pl] - (nx * a + ny * oy + nz * oz)) / nd
    rep = reported_range(th, rp, on_marker=False)
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
            Jc[:, i] = -n_p[:, i][pl] * q
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
        g = (dy * nz - dz * ny, dz * nx - cp * nz, cp * ny - dy * nx)  # dir_0 x n_0
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
        dn = (tan - n_p * (n_p * tan).sum(1, keepdims=True)) / m_norm  # (P, 3) in W
        vM = dn @ R
        gx, gy = vM[:, 0][pl], vM[:, 1][pl]
        Jn[:, i] = -(xx * (cl * gx + sl * gy) + xy * (cl * gy - sl * gx) + xz * vM[:, 2][pl] + (dn @ t)[pl]) * q
    Jn[:, 2] = q
    return PlaneRows(res, Jc, Jn)


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


__all__ = ["PlaneRows", "plane_rows"]
