"""The solver's unknowns and the data they act on (split out of lrfcal.solve, which re-exports the public names).

The core vector (:data:`CORE_NAMES`): the mount translation x, y, z, a rotation vector rx, ry, rz in frame M (the
mount's rotation is R_ref Exp(w)), the DH parameters a, alpha, b, beta, the laser-servo clock offset, a range
offset of every return and a range bias of the marker returns; then 3 nuisances per plane (:class:`PlaneSet`).
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from functools import cached_property
from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import ArrayLike, NDArray

from ..errors import InputError
from .kinematics import ESTIMATE_NAMES

if TYPE_CHECKING:  # the joint states are data; the model needs only their arrays
    from ..types import JointStates

FloatArray = NDArray[np.float64]

#: The solver's core unknowns, in this order (then 3 nuisances per plane): see the module docstring.
CORE_NAMES: tuple[str, ...] = (*ESTIMATE_NAMES, "clock_offset", "range_offset", "marker_range_bias")
N_CORE = len(CORE_NAMES)
TAU = CORE_NAMES.index("clock_offset")
ROFF = CORE_NAMES.index("range_offset")  # added to every range the scanner reports [m]
MBIAS = CORE_NAMES.index("marker_range_bias")  # added to the ranges of marker returns only [m]


@dataclass(frozen=True)
class MotorClock:
    """The motor angle at laser-clock times for a clock offset tau: lambda(t) = q(t - tau).

    stamps_s (J,) servo clock; positions_rad (J,) unwrapped joint positions; velocity_rad_s (J,) their rate,
    smoothed over about 50 ms (encoder quantisation would make the segment slopes jump), for the Jacobian.
    """

    stamps_s: FloatArray
    positions_rad: FloatArray
    velocity_rad_s: FloatArray

    @staticmethod
    def from_joints(joints: JointStates, smooth_s: float = 0.05) -> MotorClock:
        t = np.asarray(joints.stamps_s, dtype=float)
        q = np.unwrap(np.asarray(joints.positions_rad, dtype=float))
        if t.size < 2:
            raise InputError(f"joint states {joints.name}: {t.size} sample(s); need at least 2")
        period = float(np.median(np.diff(t)))
        k = int(max(1, round(0.5 * smooth_s / max(period, 1e-9))))
        lo = np.clip(np.arange(t.size) - k, 0, t.size - 1)
        hi = np.clip(np.arange(t.size) + k, 0, t.size - 1)
        v = (q[hi] - q[lo]) / np.maximum(t[hi] - t[lo], 1e-12)
        return MotorClock(t, q, v)

    def angles(self, times_s: ArrayLike, tau_s: float) -> tuple[FloatArray, FloatArray]:
        """lambda (K,) and dlambda/dt (K,) at laser times (K,) for the clock offset tau_s."""
        t = np.asarray(times_s, dtype=float) - tau_s
        return np.interp(t, self.stamps_s, self.positions_rad), np.interp(t, self.stamps_s, self.velocity_rad_s)


@dataclass(frozen=True)
class PlaneSet:
    """Non-marker returns (K2 rows) on P planes whose normals and offsets are nuisance parameters.

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

    def subset(self, m: NDArray[np.bool_]) -> PlaneSet:
        return replace(self, lam=self.lam[m], mu=self.mu[m], r=self.r[m], plane=self.plane[m],
                       times=None if self.times is None else self.times[m])

    @property
    def n_planes(self) -> int:
        return int(self.n0.shape[0])

    @cached_property
    def segments(self) -> tuple[NDArray[np.int64], NDArray[np.int64]]:
        """The rows in a stable order by plane (K2,) and each plane's [start, stop) in it (P + 1,)."""
        order = np.argsort(self.plane, kind="stable")
        return order, np.searchsorted(self.plane[order], np.arange(self.n_planes + 1))


def plane_nuisance_start(normals: FloatArray, offsets: FloatArray) -> tuple[FloatArray, FloatArray, FloatArray,
                                                                            FloatArray]:
    """Tangent bases t1, t2 (P, 3) of initial normals (P, 3) and the start nuisance vector (3P,)."""
    n0 = np.asarray(normals, dtype=float).reshape(-1, 3)
    helper = np.where(np.abs(n0[:, :1]) < 0.9, [[1.0, 0.0, 0.0]], [[0.0, 1.0, 0.0]])
    t1 = np.cross(n0, helper)
    t1 /= np.linalg.norm(t1, axis=1, keepdims=True)
    t2 = np.cross(n0, t1)
    nu0 = np.column_stack([np.zeros(len(n0)), np.zeros(len(n0)), np.asarray(offsets, dtype=float)]).ravel()
    return n0, t1, t2, nu0


def motor_lambda(lam: FloatArray, times: FloatArray | None, clock: MotorClock | None, tau: float
                 ) -> tuple[FloatArray, FloatArray | None]:
    """The motor angles to use (K,) and their rate (K,) (None when the clock offset is not estimated):
    re-interpolated at the current clock offset when it is estimated."""
    if clock is None or times is None:
        return lam, None
    return clock.angles(times, tau)


__all__ = ["CORE_NAMES", "MBIAS", "N_CORE", "ROFF", "TAU", "MotorClock", "PlaneSet", "motor_lambda",
           "plane_nuisance_start"]
