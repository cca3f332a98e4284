"""The scan plane's pose in the rotating frame M', the charts the solver moves it in, and the canonical DH branch.

The DH parameters fix the scanner's pose in M' (eq. (3) without Rz(lambda) and Rz(mu)):

    X = Tx(a) Rx(alpha) Tz(b) Rz(beta):  origin o = [a, -b sin(alpha), b cos(alpha)],  rotation R_X = Rx(alpha) Rz(beta)

X has 6 degrees of freedom and DH 4: a turn Rz(theta) about the motor axis and a shift Tz(d) along it commute with
Rz(lambda), so they belong to the mount (T_W_M Rz(theta) Tz(d)): the gauge. DH is a chart of X modulo the gauge, and
a singular one: when the scan plane is perpendicular to the motor axis (alpha = 0) b is the mount's own shift along
the axis, and a tilt of the scanner's axis towards the motor axis moves the common normal by metres (Hayati 1983,
"Robot arm geometric link parameter estimation", CDC; the same singularity of parallel joints).

A chart here is a matrix C (6, 4): its column k is the change of X that unknown k of the solver makes, as the origin's
change do (3,) in M' and a small rotation dw (3,) of the scanner about its origin, axes of M' (R_X -> Exp(dw) R_X).
The observation models (:mod:`.rays`, :mod:`.plane`) take their four scan-plane columns from such a C:

- :func:`dh_chart`: the DH parameters themselves (the covariance and every reported sigma are in DH);
- :func:`regular_chart`: four directions orthonormal to the gauge at X, regular at every geometry. The solver moves
  in it when the mount is free (so the gauge has somewhere to go) and no DH parameter is held or given a prior, and
  after every step returns to DH by :func:`canonical_dh`, the gauge put into the mount.

The canonical branch: the common normal x_c of the motor axis and the scanner's axis (DH's x axis after Rz(theta))
is the one of the two opposite choices nearer to M''s x axis (x_c . e_x >= 0): nearest to the last step's, so DH stays
continuous from step to step and a, alpha keep their signs through alpha = 0. When the two axes are parallel, x_c
points to the scanner's origin and b = 0 (the whole shift along the axis belongs to the mount).
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
from numpy.typing import ArrayLike, NDArray

from lrfcal.model.kinematics import exp_so3, log_so3, rot_x, rot_z
from lrfcal.model.unknowns import DH_SLICE

FloatArray = NDArray[np.float64]

#: |sin(alpha)| below which the scanner's axis counts as parallel to the motor axis (alpha exactly 0 or pi)
PARALLEL_SIN = 1e-12
#: the DH parameters' entries in the solver's vector (lrfcal.model.unknowns)
DH_INDEX = np.arange(DH_SLICE.start, DH_SLICE.stop)


def scan_plane_pose(dh: ArrayLike) -> tuple[FloatArray, FloatArray]:
    """The scanner's origin o (3,) and rotation R_X (3, 3) in M' of the DH parameters (a, alpha, b, beta) (4,)."""
    a, al, b, be = (float(v) for v in np.asarray(dh, dtype=float))
    return np.array([a, -b * np.sin(al), b * np.cos(al)]), rot_x(al) @ rot_z(be)


def dh_chart(dh: ArrayLike) -> FloatArray:
    """C (6, 4): the change of X per unit change of a, alpha, b, beta (module docstring)."""
    _, al, b, _ = (float(v) for v in np.asarray(dh, dtype=float))
    ca, sa = np.cos(al), np.sin(al)
    C = np.zeros((6, 4))
    C[0, 0] = 1.0  # a: along x
    C[1:3, 1] = -b * ca, -b * sa  # alpha: the origin turns about x with the axis ...
    C[3, 1] = 1.0  # ... and so does the scanner
    C[1:3, 2] = -sa, ca  # b: along the scanner's axis z_L = [0, -sin alpha, cos alpha]
    C[4:6, 3] = -sa, ca  # beta: a turn about z_L
    return C


def regular_chart(o: ArrayLike) -> FloatArray:
    """C (6, 4): an orthonormal basis of the changes of X orthogonal to the gauge at X (metres and radians, i.e. a
    rotation counted as a shift at 1 m). The gauge directions are the shift along the motor axis (e_z, 0) and the turn
    about it (e_z x o, e_z), o (3,) the scanner's origin in M' (the scanner's attitude does not enter: the turn is
    about M''s z whatever it is)."""
    o = np.asarray(o, dtype=float)
    G = np.zeros((6, 2))
    G[2, 0] = 1.0
    G[:3, 1] = -o[1], o[0], 0.0
    G[5, 1] = 1.0
    Q, _ = np.linalg.qr(np.hstack([G, np.eye(6)]))  # the first two columns span the gauge; the next four complete it
    return Q[:, 2:6] * np.where(np.diag(Q[2:6, 2:6]) < 0, -1.0, 1.0)  # signs fixed: C varies smoothly with o


def regular_chart_at(th: FloatArray) -> FloatArray:
    """:func:`regular_chart` (6, 4) at the DH parameters of the solver's vector th (lrfcal.model.unknowns)."""
    return regular_chart(scan_plane_pose(th[DH_SLICE])[0])


def move(o: ArrayLike, R_X: ArrayLike, dx: ArrayLike) -> tuple[FloatArray, FloatArray]:
    """X moved by dx = C @ step (6,) (origin change, then rotation about the origin in M' axes)."""
    dx = np.asarray(dx, dtype=float)
    return np.asarray(o, dtype=float) + dx[:3], exp_so3(dx[3:]) @ np.asarray(R_X, dtype=float)


def canonical_dh(o: ArrayLike, R_X: ArrayLike) -> tuple[FloatArray, float, float]:
    """(a, alpha, b, beta) (4,) and the gauge (theta [rad], d [m]) with X = Rz(theta) Tz(d) Tx(a) Rx(alpha) Tz(b)
    Rz(beta), in the canonical branch (module docstring): theta in (-pi/2, pi/2]."""
    o = np.asarray(o, dtype=float)
    R_X = np.asarray(R_X, dtype=float)
    z_L = R_X[:, 2]
    c = np.array([-z_L[1], z_L[0], 0.0])  # e_z x z_L = sin(alpha) x_c
    s = float(np.linalg.norm(c))
    parallel = s < PARALLEL_SIN
    x_c = (np.array([o[0], o[1], 0.0]) if parallel else c).copy()
    n = float(np.linalg.norm(x_c))
    x_c = x_c / n if n > PARALLEL_SIN else np.array([1.0, 0.0, 0.0])
    if x_c[0] < 0 or (x_c[0] == 0 and x_c[1] < 0):
        x_c = -x_c
    y_c = np.array([-x_c[1], x_c[0], 0.0])  # e_z x x_c
    sa, ca = -float(z_L @ y_c), float(z_L[2])
    alpha = float(np.arctan2(sa, ca))
    a = float(o @ x_c)
    b = 0.0 if parallel else -float(o @ y_c) / sa
    d = float(o[2]) - b * ca
    theta = float(np.arctan2(x_c[1], x_c[0]))
    Rb = rot_x(alpha).T @ rot_z(theta).T @ R_X
    beta = float(np.arctan2(Rb[1, 0], Rb[0, 0]))
    return np.array([a, alpha, b, beta]), theta, d


def gauge_distance(p: ArrayLike, q: ArrayLike, length_m: float, angle_rad: float) -> tuple[float, float, float]:
    """How far apart the scanner poses of the DH parameters p and q (4,) are, modulo the gauge: the minimum over a
    turn theta about and a shift d along the motor axis of max(|o_q - o'| / length_m, angle(R_q, R') / angle_rad),
    (o', R') the pose Rz(theta) Tz(d) X(p). Returns (that distance, the origins' offset [m] and the attitudes' angle
    [rad] at the minimum). Regular where DH differences are not (a scanner tilted a fraction of a degree towards the
    motor axis is b of metres from an untilted one in DH, and millimetres and that fraction here), and the same for
    the two DH representatives of one rig (the "turned" twin, lrfcal.model.kinematics.dh_twins). theta on a grid
    of 0.05 deg."""
    o_p, R_p = scan_plane_pose(p)
    o_q, R_q = scan_plane_pose(q)
    theta = np.linspace(-np.pi, np.pi, 7201)
    c, s = np.cos(theta), np.sin(theta)
    offset = np.hypot(c * o_p[0] - s * o_p[1] - o_q[0], s * o_p[0] + c * o_p[1] - o_q[1])  # d takes up z
    M = R_p @ R_q.T  # tr(R_q^T Rz(theta) R_p) = tr(Rz(theta) M)
    trace = c * (M[0, 0] + M[1, 1]) + s * (M[0, 1] - M[1, 0]) + M[2, 2]
    angle = np.arccos(np.clip((trace - 1.0) / 2.0, -1.0, 1.0))
    score = np.maximum(offset / length_m, angle / angle_rad)
    k = int(np.argmin(score))
    return float(score[k]), float(offset[k]), float(angle[k])


def regular_step(R_ref: FloatArray) -> Callable[[FloatArray, NDArray[np.int64], FloatArray], FloatArray]:
    """The solver's step for the regular chart: th moved by ``step`` over its entries ``free``, the scan plane's four
    in the chart at th (lrfcal.model.chart.regular_chart), back to the canonical DH with the gauge Rz(theta) Tz(d)
    put into the mount (T_W_M Rz(theta) Tz(d): t += d R e_z, R -> R Rz(theta))."""
    def step_to(th: FloatArray, free: NDArray[np.int64], step: FloatArray) -> FloatArray:
        trial = th.copy()
        trial[free] += step  # the mount, clock, intrinsics and planes; the DH entries are replaced below
        o, R_X = scan_plane_pose(th[DH_SLICE])
        o, R_X = move(o, R_X, regular_chart(o) @ step[np.searchsorted(free, DH_INDEX)])
        trial[DH_SLICE], theta, d = canonical_dh(o, R_X)
        trial[:3] += d * (R_ref @ exp_so3(trial[3:6]))[:, 2]
        trial[3:6] = log_so3(exp_so3(trial[3:6]) @ rot_z(theta))
        return trial

    return step_to


__all__ = ["PARALLEL_SIN", "canonical_dh", "dh_chart", "gauge_distance", "move", "regular_chart", "regular_chart_at",
           "regular_step", "scan_plane_pose"]
