"""The kinematic chain of the rotating laser range finder: the seed paper's eq. (3), vectorised.

Frames (paper Sec. III-A): W world/marker frame, M motor (fixed), M' (turns with the motor angle lambda),
I, I', L*, L' and L (turns with the beam angle mu). ``T_a_b`` maps points expressed in frame b into frame a.

    T_W_L = T_W_M  Rz(lambda) Tx(a) Rx(alpha) Tz(b) Rz(beta) Rz(mu)

and a return of range r is the point [r, 0, 0] in L. The mount pose T_W_M is a translation (x, y, z) followed by
R = Rz(yaw) Ry(pitch) Rx(roll), as in URDF.

Closed form used everywhere (phi = beta + mu):

    p_M = Rz(lambda) [a + r cos(phi),  r sin(phi) cos(alpha) - b sin(alpha),  r sin(phi) sin(alpha) + b cos(alpha)]

so the beam origin in M is Rz(lambda) [a, -b sin(alpha), b cos(alpha)] and its unit direction
Rz(lambda) [cos(phi), sin(phi) cos(alpha), sin(phi) sin(alpha)].
"""

from __future__ import annotations

from dataclasses import asdict, dataclass
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from lrfcal.errors import InputError

FloatArray = NDArray[np.float64]

#: elements per block in :func:`points_M_trig`
_CHUNK = 1 << 14

#: Order of the 10 calibration parameters in every vector, covariance and table.
PARAM_NAMES: tuple[str, ...] = ("x", "y", "z", "roll", "pitch", "yaw", "a", "alpha", "b", "beta")
DH_NAMES: tuple[str, ...] = ("a", "alpha", "b", "beta")
MOUNT_NAMES: tuple[str, ...] = ("x", "y", "z", "roll", "pitch", "yaw")
#: Order of the estimated quantities in every covariance and sigma vector: the mount's rotation is estimated on
#: SO(3) as a small rotation vector (rx, ry, rz) [rad] applied in frame M (R = R_hat Exp([rx, ry, rz])), so its
#: uncertainty is valid at every attitude; roll, pitch and yaw are an output format only (no sigma).
ESTIMATE_NAMES: tuple[str, ...] = ("x", "y", "z", "rx", "ry", "rz", "a", "alpha", "b", "beta")
#: Parameters that are angles (rad); the others are lengths (m).
ANGLE_NAMES: frozenset[str] = frozenset({"roll", "pitch", "yaw", "rx", "ry", "rz", "alpha", "beta"})


@dataclass(frozen=True)
class DH:
    """The four DH parameters from the motor axis to the scan plane: a [m], alpha [rad], b [m], beta [rad]."""

    a: float
    alpha: float
    b: float
    beta: float

    def as_dict(self) -> dict[str, float]:
        return {k: float(v) for k, v in asdict(self).items()}

    def vector(self) -> FloatArray:
        """(4,) a, alpha, b, beta (:data:`DH_NAMES` order)."""
        return np.array([self.a, self.alpha, self.b, self.beta], dtype=float)


@dataclass(frozen=True)
class Pose:
    """A pose T_parent_child: translation x, y, z [m]; rotation R = Rz(yaw) Ry(pitch) Rx(roll) [rad]."""

    x: float = 0.0
    y: float = 0.0
    z: float = 0.0
    roll: float = 0.0
    pitch: float = 0.0
    yaw: float = 0.0

    def matrix(self) -> FloatArray:
        """The 4x4 homogeneous transform T_parent_child."""
        return pose_matrix(self.x, self.y, self.z, self.roll, self.pitch, self.yaw)

    @staticmethod
    def from_matrix(T: ArrayLike) -> Pose:
        """Inverse of :meth:`matrix` (ZYX Euler angles; pitch in [-pi/2, pi/2])."""
        T = np.asarray(T, dtype=float)
        R = T[:3, :3]
        pitch = float(np.arcsin(np.clip(-R[2, 0], -1.0, 1.0)))
        roll = float(np.arctan2(R[2, 1], R[2, 2]))
        yaw = float(np.arctan2(R[1, 0], R[0, 0]))
        return Pose(float(T[0, 3]), float(T[1, 3]), float(T[2, 3]), roll, pitch, yaw)

    def as_dict(self) -> dict[str, float]:
        return {k: float(v) for k, v in asdict(self).items()}


@dataclass(frozen=True)
class Params:
    """The 10 calibration parameters: mount pose T_W_M and DH parameters (names as in DEVELOPERS.md)."""

    mount: Pose
    dh: DH

    def vector(self) -> FloatArray:
        """(10,) in :data:`PARAM_NAMES` order."""
        return np.array(
            [getattr(self.mount, n) for n in MOUNT_NAMES] + [getattr(self.dh, n) for n in DH_NAMES]
        )

    @staticmethod
    def from_vector(v: ArrayLike) -> Params:
        v = np.asarray(v, dtype=float).reshape(10)
        return Params(Pose(*map(float, v[:6])), DH(*map(float, v[6:])))

    def as_dict(self) -> dict[str, float]:
        return dict(zip(PARAM_NAMES, map(float, self.vector()), strict=True))


def dh_from_mapping(data: Any, where: str) -> DH:
    """Build a :class:`DH` from a mapping with exactly the keys a, alpha, b, beta; ``where`` names the source."""
    return DH(**_floats(data, DH_NAMES, where))


def pose_from_mapping(data: Any, where: str) -> Pose:
    """Build a :class:`Pose` from a mapping with exactly the keys x, y, z, roll, pitch, yaw."""
    return Pose(**_floats(data, MOUNT_NAMES, where))


def _floats(data: Any, names: tuple[str, ...], where: str) -> dict[str, float]:
    if not isinstance(data, dict):
        raise InputError(f"{where}: expected a mapping with keys {', '.join(names)}, got {data!r}")
    unknown = sorted(set(data) - set(names))
    missing = [n for n in names if n not in data]
    if unknown:
        raise InputError(f"{where}.{unknown[0]}: unknown key (expected {', '.join(names)})")
    if missing:
        raise InputError(f"{where}.{missing[0]}: missing")
    out = {}
    for n in names:
        v = data[n]
        if isinstance(v, bool) or not isinstance(v, (int, float)) or not np.isfinite(v):
            raise InputError(f"{where}.{n}: expected a finite number, got {v!r}")
        out[n] = float(v)
    return out


def is_placeholder_dh(dh: object) -> bool:
    """Whether DH values (a mapping or an object with a, alpha, b, beta) are all 0: the placeholder a rig file from
    ``lrfcal inspect`` holds when the recording did not determine a proposal."""
    values = dh if isinstance(dh, dict) else {n: getattr(dh, n, None) for n in DH_NAMES}
    return all(values.get(n, None) == 0.0 for n in DH_NAMES)


def refuse_placeholder_dh(dh: object, where: str, before: str) -> None:
    """The one check of calibrate and reproject on the nominal DH: the placeholder (:func:`is_placeholder_dh`) is
    refused.

    Raises:
        InputError: ``dh`` is the placeholder (the line names ``where``, the key ``dh`` and what to do ``before``).
    """
    if is_placeholder_dh(dh):
        raise InputError(f"{where}: dh: a, alpha, b and beta are all 0, the placeholder `lrfcal inspect` writes: fill "
                         f"in the design values (m, rad; docs/formats.md) before {before}")


# --- elementary transforms ----------------------------------------------------------------------------------


def rot_x(t: ArrayLike) -> FloatArray:
    """Rotation matrices about x, shape (..., 3, 3) for angles of shape (...)."""
    t = np.asarray(t, dtype=float)
    c, s = np.cos(t), np.sin(t)
    if t.ndim == 0:  # one angle: the same entries without the stacks' temporaries
        return np.array([[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]])
    o, z = np.ones_like(t), np.zeros_like(t)
    return np.stack([np.stack([o, z, z], -1), np.stack([z, c, -s], -1), np.stack([z, s, c], -1)], -2)


def rot_y(t: ArrayLike) -> FloatArray:
    """Rotation matrices about y, shape (..., 3, 3)."""
    t = np.asarray(t, dtype=float)
    c, s = np.cos(t), np.sin(t)
    if t.ndim == 0:  # one angle: the same entries without the stacks' temporaries
        return np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])
    o, z = np.ones_like(t), np.zeros_like(t)
    return np.stack([np.stack([c, z, s], -1), np.stack([z, o, z], -1), np.stack([-s, z, c], -1)], -2)


def rot_z(t: ArrayLike) -> FloatArray:
    """Rotation matrices about z, shape (..., 3, 3)."""
    t = np.asarray(t, dtype=float)
    c, s = np.cos(t), np.sin(t)
    if t.ndim == 0:  # one angle: the same entries without the stacks' temporaries
        return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    o, z = np.ones_like(t), np.zeros_like(t)
    return np.stack([np.stack([c, -s, z], -1), np.stack([s, c, z], -1), np.stack([z, z, o], -1)], -2)


def rpy_matrix(roll: float, pitch: float, yaw: float) -> FloatArray:
    """R = Rz(yaw) Ry(pitch) Rx(roll), shape (3, 3) (URDF convention)."""
    return rot_z(yaw) @ rot_y(pitch) @ rot_x(roll)


def pose_matrix(x: float, y: float, z: float, roll: float, pitch: float, yaw: float) -> FloatArray:
    """4x4 transform: translation (x, y, z), rotation Rz(yaw) Ry(pitch) Rx(roll)."""
    T = np.eye(4)
    T[:3, :3] = rpy_matrix(roll, pitch, yaw)
    T[:3, 3] = (x, y, z)
    return T


def homogeneous(R: ArrayLike, t: ArrayLike) -> FloatArray:
    """Stack rotations (..., 3, 3) and translations (..., 3) into transforms (..., 4, 4)."""
    R = np.asarray(R, dtype=float)
    t = np.asarray(t, dtype=float)
    T = np.zeros(R.shape[:-2] + (4, 4))
    T[..., :3, :3] = R
    T[..., :3, 3] = t
    T[..., 3, 3] = 1.0
    return T


# --- eq. (3) ------------------------------------------------------------------------------------------------


def chain_T_M_L(lambda_rad: ArrayLike, mu_rad: ArrayLike, dh: DH) -> FloatArray:
    """T_M_L by multiplying the paper's elementary matrices, eqs. (4)-(9): shape (K, 4, 4) for K angles.

    This is the literal product, kept as the reference the closed forms below are tested against.
    """
    lam = np.atleast_1d(np.asarray(lambda_rad, dtype=float))
    mu = np.atleast_1d(np.asarray(mu_rad, dtype=float))
    lam, mu = np.broadcast_arrays(lam, mu)
    K = lam.shape[0]
    Tz_lam = homogeneous(rot_z(lam), np.zeros((K, 3)))
    Tx_a = homogeneous(np.eye(3), [dh.a, 0.0, 0.0])
    Rx_alpha = homogeneous(rot_x(dh.alpha), np.zeros(3))
    Tz_b = homogeneous(np.eye(3), [0.0, 0.0, dh.b])
    Rz_beta = homogeneous(rot_z(dh.beta), np.zeros(3))
    Rz_mu = homogeneous(rot_z(mu), np.zeros((K, 3)))
    return Tz_lam @ Tx_a @ Rx_alpha @ Tz_b @ Rz_beta @ Rz_mu


def beam_rays_M(lambda_rad: ArrayLike, mu_rad: ArrayLike, dh: DH) -> tuple[FloatArray, FloatArray]:
    """Origins and unit directions of beams in the motor frame M.

    Args:
        lambda_rad: (K,) motor angles.
        mu_rad: (K,) beam angles (LaserScan bearing).
    Returns:
        origins_M (K, 3), directions_M (K, 3).
    """
    lam = np.asarray(lambda_rad, dtype=float)
    phi = dh.beta + np.asarray(mu_rad, dtype=float)
    lam, phi = np.broadcast_arrays(lam, phi)
    return beam_rays_M_trig(np.cos(lam), np.sin(lam), np.cos(phi), np.sin(phi), dh)


#: cos and sin of K beams' motor angles and of their phi = beta + mu, each (K,) (:func:`beam_trig`)
BeamTrig = tuple[FloatArray, FloatArray, FloatArray, FloatArray]


def beam_trig(lambda_rad: FloatArray, mu_rad: FloatArray, dh: DH) -> BeamTrig:
    """cos and sin of the motor angles and of phi = beta + mu (each (K,)), as :func:`points_M` and
    :func:`beam_rays_M` compute them: for :func:`points_M_trig` and :func:`beam_rays_M_trig` of the same beams
    (elementwise, so those of a subset of the beams are these values' subset, bit for bit)."""
    lam = np.asarray(lambda_rad, dtype=float)
    phi = dh.beta + np.asarray(mu_rad, dtype=float)
    return np.cos(lam), np.sin(lam), np.cos(phi), np.sin(phi)


def beam_rays_M_trig(cos_lambda: FloatArray, sin_lambda: FloatArray, cos_phi: FloatArray, sin_phi: FloatArray,
                     dh: DH) -> tuple[FloatArray, FloatArray]:
    """:func:`beam_rays_M` from cos / sin of lambda and of phi = beta + mu (all of one shape (K,))."""
    cl, sl = cos_lambda, sin_lambda
    ca, sa = np.cos(dh.alpha), np.sin(dh.alpha)
    # before Rz(lambda)
    ox, oy, oz = dh.a, -dh.b * sa, dh.b * ca
    dx, dy, dz = cos_phi, sin_phi * ca, sin_phi * sa
    origins = np.stack([cl * ox - sl * oy, sl * ox + cl * oy, np.full(cl.shape, oz)], -1)
    dirs = np.stack([cl * dx - sl * dy, sl * dx + cl * dy, dz], -1)
    return origins, dirs


def points_M(ranges_m: ArrayLike, lambda_rad: ArrayLike, mu_rad: ArrayLike, dh: DH) -> FloatArray:
    """Returns [r, 0, 0] in L expressed in the motor frame M, shape (K, 3)."""
    lam = np.asarray(lambda_rad, dtype=float)
    phi = dh.beta + np.asarray(mu_rad, dtype=float)
    r = np.asarray(ranges_m, dtype=float)
    shape = np.broadcast_shapes(lam.shape, phi.shape, r.shape)
    lam, phi, r = (np.broadcast_to(v, shape) for v in (lam, phi, r))
    return points_M_trig(r, np.cos(lam), np.sin(lam), np.cos(phi), np.sin(phi), dh)


def dh_twins(dh: DH) -> tuple[tuple[str, DH, FloatArray], ...]:
    """The exact symmetries of eq. (3): the three other DH parameter sets whose cloud in M is the cloud of ``dh``
    moved by a fixed isometry Q of M that commutes with the motor's turn, points_M(r, lambda, mu, twin) =
    Q points_M(r, lambda, mu, dh) for every range, motor angle and bearing. Each as (name, twin, Q (3, 3)):

    - "turned": (-a, -alpha, b, beta + pi), Q = Rz(pi), the mount turned by pi about the motor axis: the same rig
      in another DH representative (the mount absorbs Q);
    - "mirrored": (a, -alpha, -b, beta), Q = diag(1, 1, -1), the rig's mirror image through the plane normal to
      the motor axis;
    - "mirrored, turned": (-a, alpha, -b, beta + pi), Q = -I.

    A mirror image explains the same data with the marker map mirrored too (tape distances fix the map only up to
    a reflection; flatness cannot tell a cloud from its mirror image): only the rig's drawings can tell it from the
    rig (lrfcal.estimate.checks.mirror_check)."""
    turned = wrap_angle(dh.beta + np.pi).item()
    return (
        ("turned", DH(a=-dh.a, alpha=-dh.alpha, b=dh.b, beta=turned), np.diag([-1.0, -1.0, 1.0])),
        ("mirrored", DH(a=dh.a, alpha=-dh.alpha, b=-dh.b, beta=dh.beta), np.diag([1.0, 1.0, -1.0])),
        ("mirrored, turned", DH(a=-dh.a, alpha=dh.alpha, b=-dh.b, beta=turned), -np.eye(3)),
    )


def points_M_trig(
    ranges_m: FloatArray, cos_lambda: FloatArray, sin_lambda: FloatArray, cos_phi: FloatArray,
    sin_phi: FloatArray, dh: DH,
) -> FloatArray:
    """:func:`points_M` from precomputed cos / sin of lambda and of phi = beta + mu (all of one shape (...)).

    The same arithmetic as origin + r * direction of :func:`beam_rays_M` (bit for bit), written column by
    column into one (..., 3) array without (..., 3) temporaries: for large clouds, and for reprojecting the
    same beams with several DH sets (cos / sin of lambda shared; phi depends on the DH's beta).
    """
    r, cl, sl, cp, sp = (np.asarray(v, dtype=float) for v in (ranges_m, cos_lambda, sin_lambda, cos_phi, sin_phi))
    shape = r.shape
    r, cl, sl, cp, sp = (v.reshape(-1) for v in (r, cl, sl, cp, sp))
    ca, sa = np.cos(dh.alpha), np.sin(dh.alpha)
    ox, oy, oz = dh.a, -dh.b * sa, dh.b * ca
    K = r.size
    out = np.empty((K, 3))
    step = max(1, min(K, _CHUNK))  # elementwise, so chunking changes no bit; the temporaries stay in cache
    t, u, o, dy = (np.empty(step) for _ in range(4))
    for s in range(0, K, step):
        e = min(K, s + step)
        m = e - s
        r_, cl_, sl_, cp_, sp_ = r[s:e], cl[s:e], sl[s:e], cp[s:e], sp[s:e]
        t_, u_, o_, dy_ = t[:m], u[:m], o[:m], dy[:m]
        np.multiply(sp_, ca, out=dy_)  # dy = sin(phi) cos(alpha)
        # x: (cl ox - sl oy) + r (cl dx - sl dy), dx = cos(phi)
        np.multiply(cl_, cp_, out=t_)
        np.multiply(sl_, dy_, out=u_)
        t_ -= u_
        t_ *= r_
        np.multiply(cl_, ox, out=o_)
        np.multiply(sl_, oy, out=u_)
        o_ -= u_
        np.add(o_, t_, out=out[s:e, 0])
        # y: (sl ox + cl oy) + r (sl dx + cl dy)
        np.multiply(sl_, cp_, out=t_)
        np.multiply(cl_, dy_, out=u_)
        t_ += u_
        t_ *= r_
        np.multiply(sl_, ox, out=o_)
        np.multiply(cl_, oy, out=u_)
        o_ += u_
        np.add(o_, t_, out=out[s:e, 1])
        # z: oz + r dz, dz = sin(phi) sin(alpha)
        np.multiply(sp_, sa, out=t_)
        t_ *= r_
        np.add(oz, t_, out=out[s:e, 2])
    return out.reshape(shape + (3,))


def transform_points(T: ArrayLike, points: ArrayLike) -> FloatArray:
    """Apply a 4x4 transform T_a_b to points (..., 3) expressed in b; returns them in a."""
    T = np.asarray(T, dtype=float)
    return np.asarray(points, dtype=float) @ T[:3, :3].T + T[:3, 3]


def points_W(ranges_m: ArrayLike, lambda_rad: ArrayLike, mu_rad: ArrayLike, params: Params) -> FloatArray:
    """Returns in the world frame W: T_W_M p_M, shape (K, 3)."""
    return transform_points(params.mount.matrix(), points_M(ranges_m, lambda_rad, mu_rad, params.dh))


def beam_rays_W(params: Params, lambda_rad: ArrayLike, mu_rad: ArrayLike) -> tuple[FloatArray, FloatArray]:
    """Beam origins (K, 3) and unit directions (K, 3) in W for motor angles and bearings (K,):
    :func:`beam_rays_M` moved by T_W_M."""
    return _moved(params, *beam_rays_M(lambda_rad, mu_rad, params.dh))


def beam_rays_W_trig(params: Params, trig: BeamTrig) -> tuple[FloatArray, FloatArray]:
    """:func:`beam_rays_W` of beams by their :func:`beam_trig`."""
    return _moved(params, *beam_rays_M_trig(*trig, params.dh))


def points_W_trig(ranges_m: FloatArray, trig: BeamTrig, params: Params) -> FloatArray:
    """:func:`points_W` of returns (K,) by their beams' :func:`beam_trig` (the same bits)."""
    return transform_points(params.mount.matrix(), points_M_trig(ranges_m, *trig, params.dh))


def _moved(params: Params, o_M: FloatArray, d_M: FloatArray) -> tuple[FloatArray, FloatArray]:
    T = params.mount.matrix()
    return transform_points(T, o_M), d_M @ T[:3, :3].T


# --- SO(3) -------------------------------------------------------------------------------------------------


def skew(v: ArrayLike) -> FloatArray:
    """[v]x, shape (..., 3, 3), with [v]x u = v x u for v of shape (..., 3)."""
    v = np.asarray(v, dtype=float)
    if v.ndim == 1:  # one vector: the same entries without the stacks' temporaries
        x, y, w = v
        return np.array([[0.0, -w, y], [w, 0.0, -x], [-y, x, 0.0]])
    z = np.zeros(v.shape[:-1])
    x, y, w = v[..., 0], v[..., 1], v[..., 2]
    return np.stack([np.stack([z, -w, y], -1), np.stack([w, z, -x], -1), np.stack([-y, x, z], -1)], -2)


def exp_so3(w: ArrayLike) -> FloatArray:
    """Rotation matrix (3, 3) of the rotation vector w (3,) [rad] (Rodrigues' formula)."""
    w = np.asarray(w, dtype=float).reshape(3)
    t = float(np.linalg.norm(w))
    K = skew(w)
    if t < 1e-8:
        return np.eye(3) + K + 0.5 * K @ K
    return np.eye(3) + np.sin(t) / t * K + (1.0 - np.cos(t)) / t**2 * K @ K


def log_so3(R: ArrayLike) -> FloatArray:
    """Rotation vector (3,) [rad] of a rotation matrix (3, 3), angle in [0, pi]."""
    R = np.asarray(R, dtype=float)
    c = float(np.clip((np.trace(R) - 1.0) / 2.0, -1.0, 1.0))
    t = float(np.arccos(c))
    v = np.array([R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1]])
    if t < 1e-6:
        return 0.5 * v
    if np.pi - t > 1e-4:
        return t / (2.0 * np.sin(t)) * v
    # near pi: the axis from the symmetric part, its sign from the antisymmetric part
    B = 0.5 * (R + np.eye(3))
    axis = np.sqrt(np.clip(np.diag(B), 0.0, None))
    i = int(np.argmax(axis))
    axis = B[i] / max(axis[i], 1e-12)
    axis /= np.linalg.norm(axis)
    if axis @ v < 0:
        axis = -axis
    return t * axis


def right_jacobian_so3(w: ArrayLike) -> FloatArray:
    """J_r(w) (3, 3): Exp(w + dw) = Exp(w) Exp(J_r(w) dw) to first order."""
    w = np.asarray(w, dtype=float).reshape(3)
    t = float(np.linalg.norm(w))
    K = skew(w)
    if t < 1e-6:
        return np.eye(3) - 0.5 * K + K @ K / 6.0
    return np.eye(3) - (1.0 - np.cos(t)) / t**2 * K + (t - np.sin(t)) / t**3 * K @ K


def rotation_angle(R: ArrayLike) -> float:
    """The angle [rad] of a rotation matrix (3, 3), in [0, pi]."""
    return float(np.arccos(np.clip((np.trace(np.asarray(R, dtype=float)) - 1.0) / 2.0, -1.0, 1.0)))


def wrap_angle(a: ArrayLike) -> FloatArray:
    """Wrap angles to [-pi, pi)."""
    return (np.asarray(a, dtype=float) + np.pi) % (2 * np.pi) - np.pi


__all__ = ["ANGLE_NAMES", "BeamTrig", "DH", "DH_NAMES", "ESTIMATE_NAMES", "MOUNT_NAMES", "PARAM_NAMES", "Params",
           "Pose", "beam_rays_M", "beam_rays_M_trig", "beam_rays_W", "beam_rays_W_trig", "beam_trig", "chain_T_M_L",
           "dh_from_mapping", "dh_twins", "exp_so3", "homogeneous", "is_placeholder_dh", "log_so3", "points_M",
           "points_M_trig", "points_W", "points_W_trig", "pose_from_mapping", "pose_matrix", "refuse_placeholder_dh",
           "right_jacobian_so3", "rot_x", "rot_y", "rot_z", "rotation_angle", "rpy_matrix", "skew", "transform_points",
           "wrap_angle"]
