"""The per-beam motor angle: the joint states interpolated at the beam's laser time minus the clock offset.

    lambda_k = s q(t_k - tau)

q: the joint states (servo clock), interpolated linearly; t_k: the beam's time (laser clock); tau: the clock offset
(laser stamp - servo stamp); s: the motor-angle scale (1 for a servo whose reported angle is its true angle; a
gear ratio or a wrong counts-per-turn makes it differ). Its partial derivatives are the motor-angle columns of every
observation model's Jacobian (a model multiplies dX/dlambda = z x X by each, :func:`motor_angles`), so an unknown
acting on the motor angle (a clock offset, a gear ratio) is written here once.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol

import numpy as np
from numpy.typing import ArrayLike, NDArray

from ..errors import InputError
from .unknowns import SCALE, TAU

FloatArray = NDArray[np.float64]


class JointSamples(Protocol):
    """What the model reads of joint states (lrfcal.types.JointStates): their stamps (J,) on the servo clock, the
    positions (J,) and the joint's name. A protocol, so the model does not import the data layer."""

    stamps_s: ArrayLike
    positions_rad: ArrayLike
    name: str


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
    def from_joints(joints: JointSamples, smooth_s: float = 0.05) -> MotorClock:
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
class MotorAngles:
    """The motor angle of K beams (K,) and its partial derivatives: (core index, dlambda/dtheta (K,)) per unknown
    that acts on it (none when the angles are data, e.g. interpolated once at a held clock offset)."""

    lam: FloatArray
    partials: tuple[tuple[int, FloatArray], ...] = ()


def motor_angles(th: FloatArray, lam: FloatArray, times: FloatArray | None, clock: MotorClock | None) -> MotorAngles:
    """The beams' motor angles at the unknowns ``th`` (N_CORE + ...,): the joint angle q re-interpolated at the clock
    offset th[TAU] when it is estimated (``clock`` and the beam ``times`` (K,) given; dq/dtau = -omega, the joint's
    smoothed rate), else ``lam`` (K,) as given (interpolated once at the held clock offset); times the motor-angle
    scale th[SCALE] (dlambda/ds = q)."""
    s = th[SCALE]
    if clock is None or times is None:
        q = np.asarray(lam, dtype=float)
        return MotorAngles(s * q, ((SCALE, q),))
    q, omega = clock.angles(times, th[TAU])
    return MotorAngles(s * q, ((TAU, -s * omega), (SCALE, q)))


__all__ = ["JointSamples", "MotorAngles", "MotorClock", "motor_angles"]
