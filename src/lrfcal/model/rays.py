"""Each beam's origin and unit direction in W (the seed paper's eq. (3)) and their analytic Jacobian with respect to
the core unknowns (lrfcal.model.unknowns).

Per beam k with motor angle lambda_k (lrfcal.model.motor) and true bearing mu_k (lrfcal.model.scanner),
phi_k = beta + mu_k:

    o_M = Rz(lambda) [a, -b sin(alpha), b cos(alpha)]                              beam origin in M
    d_M = Rz(lambda) [cos(phi), sin(phi) cos(alpha), sin(phi) sin(alpha)]           unit direction in M
    o = R o_M + t,  d = R d_M                                                       in W, R = R_ref Exp(w)

Jacobian (X_j = dX/dtheta_j):
    translation: o_j = e_j, d_j = 0;
    rotation vector w_j: o_j = -R [o_M]x J_r(w) e_j, d_j = -R [d_M]x J_r(w) e_j (J_r: SO(3) right Jacobian);
    DH parameter p: o_j = R Rz(lambda) d(o_loc)/dp, d_j = R Rz(lambda) d(d_loc)/dp with
      d o_loc/da = (1,0,0), d o_loc/dalpha = (0, -b ca, -b sa), d o_loc/db = (0, -sa, ca), d o_loc/dbeta = 0,
      d d_loc/dalpha = (0, -sphi sa, sphi ca), d d_loc/dbeta = (-sphi, cphi ca, cphi sa), others 0;
    or, in another chart of the scan plane's pose (lrfcal.model.chart; the solver's regular one), the unknown k with
      the chart column (do_k, dw_k): o_j = R Rz(lambda) do_k, d_j = R Rz(lambda) (dw_k x d_loc);
    an unknown acting on the motor angle: o_j = R (z x o_M) dlambda/dtheta_j, likewise d_j;
    an unknown acting on the bearing: o_j = 0, d_j = d_beta dmu/dtheta_j.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from lrfcal.model.kinematics import exp_so3, right_jacobian_so3
from lrfcal.model.motor import MotorAngles
from lrfcal.model.scanner import true_bearing
from lrfcal.model.unknowns import N_CORE

FloatArray = NDArray[np.float64]


def beam_rays(
    core: FloatArray, R_ref: FloatArray, motor: MotorAngles, mu: FloatArray, jac: bool, mount_jac: bool = True,
    chart: FloatArray | None = None,
) -> tuple[FloatArray, FloatArray, FloatArray | None, FloatArray | None]:
    """Beam origins o (K, 3) and unit directions d (K, 3) in W and their Jacobians (K, 3, N_CORE) with respect to
    the core unknowns (module docstring); the mount's columns are left 0 when ``mount_jac`` is False (a held
    mount), the motor angle's when ``motor`` carries no partials. ``chart`` (6, 4): what the four scan-plane
    columns are derivatives by (lrfcal.model.chart; None: the DH parameters)."""
    t, w = core[:3], core[3:6]
    a, al, b, be = core[6:10]
    bearing = true_bearing(core, np.atleast_1d(mu))
    lam, phi = np.broadcast_arrays(np.atleast_1d(motor.lam), be + bearing.mu)
    K = lam.size
    cl, sl = np.cos(lam), np.sin(lam)
    ca, sa = np.cos(al), np.sin(al)
    cp, sp = np.cos(phi), np.sin(phi)
    R = R_ref @ exp_so3(w)

    def rz(v: FloatArray) -> FloatArray:  # Rz(lambda_k) v_k for v (K, 3) or (3,)
        out = np.empty((K, 3))
        # one vector for every beam: its entries as scalars (the same products as its broadcast columns)
        v0, v1, v2 = v if v.ndim == 1 else (v[:, 0], v[:, 1], v[:, 2])
        np.subtract(cl * v0, sl * v1, out=out[:, 0])
        np.add(sl * v0, cl * v1, out=out[:, 1])
        out[:, 2] = v2
        return out

    o_M = rz(np.array([a, -b * sa, b * ca]))
    d_loc = np.stack([cp, sp * ca, sp * sa], -1)  # the direction before Rz(lambda)
    d_M = rz(d_loc)
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
            Jo[:, :, 3 + j] = -_cross(o_M, Jr[:, j]) @ R.T
            Jd[:, :, 3 + j] = -_cross(d_M, Jr[:, j]) @ R.T
    z0 = np.zeros(K)
    if chart is None:  # the DH parameters: the chart columns below in closed form
        Jo[:, :, 6] = rz(np.array([1.0, 0.0, 0.0])) @ R.T
        Jo[:, :, 7] = rz(np.array([0.0, -b * ca, -b * sa])) @ R.T
        Jo[:, :, 8] = rz(np.array([0.0, -sa, ca])) @ R.T
        Jd[:, :, 7] = rz(np.stack([z0, -sp * sa, sp * ca], -1)) @ R.T
        Jd[:, :, 9] = turn = rz(np.stack([-sp, cp * ca, cp * sa], -1)) @ R.T
    else:
        for k in range(4):
            Jo[:, :, 6 + k] = rz(chart[:3, k]) @ R.T
            Jd[:, :, 6 + k] = rz(_cross(chart[3:, k], d_loc)) @ R.T
        turn = rz(_cross(np.array([0.0, -sa, ca]), d_loc)) @ R.T
    for j, dmu in bearing.partials:  # a turn about the scanner's axis, as beta's
        Jd[:, :, j] = np.broadcast_to(dmu, (K,))[:, None] * turn
    if motor.partials:  # d/dlambda of Rz(lambda) v is z x (Rz v)
        zo = np.stack([-o_M[:, 1], o_M[:, 0], z0], -1) @ R.T
        zd = np.stack([-d_M[:, 1], d_M[:, 0], z0], -1) @ R.T
        for j, dlam in motor.partials:
            Jo[:, :, j] = dlam[:, None] * zo
            Jd[:, :, j] = dlam[:, None] * zd
    return o, d, Jo, Jd


def _cross(a: FloatArray, b: FloatArray) -> FloatArray:
    """a x b (K, 3) of a (K, 3) or (3,) and b (3,) or (K, 3): np.cross's products and differences, in its order (the
    same bits), without its axis handling (a few microseconds a call, the cost of the product itself here)."""
    a0, a1, a2 = (a[..., i] for i in range(3))
    b0, b1, b2 = (b[..., i] for i in range(3))
    return np.stack([a1 * b2 - a2 * b1, a2 * b0 - a0 * b2, a0 * b1 - a1 * b0], -1)


__all__ = ["beam_rays"]
