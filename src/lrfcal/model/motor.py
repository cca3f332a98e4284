"""The per-beam motor angle: the joint states interpolated at the beam's laser time minus the clock offset.

    lambda_k = s q(t_k - tau)

q: the joint states (servo clock), interpolated linearly; t_k: the beam's time (laser clock); tau: the clock offset
(laser stamp - servo stamp); s: the motor-angle scale (1 for a servo whose reported angle is its true angle; a
gear ratio or a wrong counts-per-turn makes it differ). Its partial derivatives are the motor-angle columns of every
observation model's Jacobian (a model multiplies dX/dlambda = z x X by each, :func:`motor_angles`), so an unknown
acting on the motor angle (a clock offset, a gear ratio) is written here once.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Protocol

import numpy as np
from numpy.typing import ArrayLike, NDArray

from lrfcal.errors import InputError
from lrfcal.model.unknowns import SCALE, TAU

FloatArray = NDArray[np.float64]


class JointSamples(Protocol):
    """What the model reads of joint states (lrfcal.types.JointStates): their stamps (J,) on the servo clock, the
    positions (J,) and the joint's name. A protocol, so the model does not import the data layer."""

    @property
    def stamps_s(self) -> ArrayLike: ...
    @property
    def positions_rad(self) -> ArrayLike: ...
    @property
    def name(self) -> str: ...


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

    def angle(self, times_s: ArrayLike, tau_s: float) -> FloatArray:
        """lambda (K,) at laser times (K,) for the clock offset tau_s (the first of :meth:`angles`)."""
        return np.interp(np.asarray(times_s, dtype=float) - tau_s, self.stamps_s, self.positions_rad)

    def angles(self, times_s: ArrayLike, tau_s: float) -> tuple[FloatArray, FloatArray]:
        """lambda (K,) and dlambda/dt (K,) at laser times (K,) for the clock offset tau_s."""
        t = np.asarray(times_s, dtype=float) - tau_s
        return np.interp(t, self.stamps_s, self.positions_rad), np.interp(t, self.stamps_s, self.velocity_rad_s)


@dataclass(frozen=True)
class Clock:
    """The laser clock against the servo's, as an estimate takes it: the clock offset tau (``offset_s``, where the
    estimate starts, or its value where held) and the joint states it is estimated by (``motor``; None: held)."""

    motor: MotorClock | None = None
    offset_s: float = 0.0


#: no joint states: the clock offset held at 0
NO_CLOCK = Clock()


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


#: a pause between joint states longer than this many of their median periods is a gap that linear interpolation
#: bridges blindly (lrfcal.model.motor.joint_gaps)
GAP_PERIODS = 4.0
#: the velocity on each side of a gap, and the recorded motion's top speed, are slopes over this long a window of
#: samples (the encoder's step blurs the slope of a single period)
EDGE_WINDOW_S = 0.1
#: the motion across a gap counts as steady when the velocities just before it, across it (its chord) and just after
#: it agree within this share of the recorded top speed (plus what the encoder's step leaves of a slope)
STEADY_SHARE = 0.1
#: the recorded motion's top speed: this percentile of the window slopes' magnitudes (a jittery stream's outliers
#: left out)
TOP_PERCENTILE = 98.0


@dataclass(frozen=True)
class JointGap:
    """A gap in the joint states that the motor angle's linear interpolation bridges: ``start_s``, ``end_s`` the
    samples on its two sides (servo clock); the velocity just before it, across it (its chord) and just after it
    [rad/s] (NaN where a side has fewer than 2 samples); ``hides``: the motion it may hide, "" when the motion
    across it is steady (the interpolation is right there)."""

    start_s: float
    end_s: float
    before_rad_s: float
    across_rad_s: float
    after_rad_s: float
    hides: str

    @property
    def length_s(self) -> float:
        return self.end_s - self.start_s

    def describe(self, origin_s: float = 0.0) -> str:
        """One phrase naming the gap: its times (servo clock, after ``origin_s``, e.g. the first joint state's stamp),
        length and velocities, and what it may hide."""
        text = (f"no joint states for {self.length_s:.3g} s ({self.start_s - origin_s:.3f}-{self.end_s - origin_s:.3f} "
                f"s after the first joint state; {self.before_rad_s:+.3f} rad/s before, {self.across_rad_s:+.3f} "
                f"across, {self.after_rad_s:+.3f} after)")
        return f"{text}, which may hide {self.hides}" if self.hides else text


def _window_slopes(t: FloatArray, q: FloatArray, k: int, period: float) -> FloatArray:
    """(J - k,) slopes (q[i + k] - q[i]) / (t[i + k] - t[i]) of windows without a gap (NaN for those with one)."""
    dt = t[k:] - t[:-k]
    return np.where(dt <= (k - 1 + GAP_PERIODS) * period, (q[k:] - q[:-k]) / np.maximum(dt, 1e-12), np.nan)


def joint_gaps(stamps_s: ArrayLike, positions_rad: ArrayLike) -> tuple[JointGap, ...]:
    """Every pause between joint states (J,) longer than GAP_PERIODS median periods, and the motion it may hide.

    Linear interpolation is right across a gap only where the motor kept its speed through it. A gap may hide:
    a reversal (the velocities before and after it point opposite ways), a stop or a change of speed (the
    velocities before, across (its chord: the position change over its length) and after it disagree by more than
    STEADY_SHARE of the recorded top speed), or, at a standstill on both sides, a whole pass of the sweep (a gap
    longer than the time the servo takes from one end of the recorded motion to the other at its top speed).
    stamps_s (J,) increasing, positions_rad (J,) (unwrapped here)."""
    t = np.asarray(stamps_s, dtype=float)
    q = np.unwrap(np.asarray(positions_rad, dtype=float))
    if t.size < 3:
        return ()
    dt = np.diff(t)
    period = float(np.median(dt))
    starts = np.flatnonzero(dt > GAP_PERIODS * period)
    if not starts.size:
        return ()
    k = int(max(1, round(EDGE_WINDOW_S / max(period, 1e-12))))
    k = min(k, t.size - 1)
    slopes = _window_slopes(t, q, k, period)
    top = float(np.nanpercentile(np.abs(slopes), TOP_PERCENTILE)) if np.isfinite(slopes).any() else 0.0
    steps = np.abs(np.diff(q))
    quantum = float(steps[steps > 1e-12].min()) if np.any(steps > 1e-12) else 0.0
    tol = STEADY_SHARE * top + 2.0 * quantum / (k * period)
    sweep_s = float(np.ptp(q)) / top if top > 0 else math.inf
    return tuple(_gap(t, q, int(i), k, tol, sweep_s) for i in starts)


def _side_slope(t: FloatArray, q: FloatArray, i0: int, i1: int) -> float:
    """The slope over samples i0..i1 (clipped to the array; NaN for fewer than 2 samples)."""
    i0, i1 = max(i0, 0), min(i1, t.size - 1)
    return float((q[i1] - q[i0]) / (t[i1] - t[i0])) if i1 > i0 else math.nan


def _gap(t: FloatArray, q: FloatArray, i: int, k: int, tol: float, sweep_s: float) -> JointGap:
    """The gap between samples i and i + 1 (:func:`joint_gaps`)."""
    before, after = _side_slope(t, q, i - k, i), _side_slope(t, q, i + 1, i + 1 + k)
    across = float((q[i + 1] - q[i]) / (t[i + 1] - t[i]))
    known = [v for v in (before, after) if math.isfinite(v)]
    moving = [np.sign(v) for v in (*known, across) if abs(v) > tol]
    if len(set(moving)) > 1:
        hides = "a reversal of the servo"
    elif any(abs(v - across) > tol for v in known) or (len(known) == 2 and abs(known[0] - known[1]) > tol):
        hides = "a stop or a change of the servo's speed"
    elif not moving and t[i + 1] - t[i] > sweep_s:
        hides = "a whole pass of the sweep"
    else:
        hides = ""
    return JointGap(float(t[i]), float(t[i + 1]), before, across, after, hides)


#: the clock offset (laser stamp - servo stamp) a calibration starts from or reports lies within this [s]: beyond
#: it the two clocks differ rather than lag (the bag reader measures such an offset from the receive times and
#: applies it, lrfcal.io.bag.COARSE_OFFSET_MIN_S); what is left is the stamping and transport latency
MAX_CLOCK_OFFSET_S = 1.0
#: ... and within this share of the sweep's shortest pass (the time between two turnarounds; a one-way sweep or a
#: spin: the recording): an offset tau moves the motor angles of the two directions apart by twice the sweep's speed
#: times tau, and the solve only finds the offset from a start within a few degrees of it (simulated tunnel_v at
#: 10 deg/s: from 1 s, 10 deg, it converged to the true 0; from 2 s, 20 deg, it reported +1.94 s, all checks
#: passed), which a sixteenth of a pass keeps (11 deg of a 180 deg sweep); an offset of a whole pass would even
#: map each pass onto the other one mirrored (the sweep aliases)
CLOCK_OFFSET_PASS_SHARE = 1.0 / 16.0


def clock_offset_bound_s(pass_durations_s: ArrayLike) -> float:
    """The largest clock offset [s] a calibration may start from or report: the smaller of MAX_CLOCK_OFFSET_S and
    CLOCK_OFFSET_PASS_SHARE of the shortest pass (``pass_durations_s`` (P,), the sweep's passes' durations; a
    one-way sweep has one pass, the recording)."""
    d = np.asarray(pass_durations_s, dtype=float)
    d = d[np.isfinite(d) & (d > 0)]
    if d.size == 0:
        return MAX_CLOCK_OFFSET_S
    return float(min(MAX_CLOCK_OFFSET_S, CLOCK_OFFSET_PASS_SHARE * d.min()))


#: samples on each side of a joint sample that its dequantising fit takes (lrfcal.model.motor.dequantised)
DEQUANTISE_HALF_WINDOW = 8
#: a fit that leaves a sample of its window more than this many steps from its reading is not used (the readings
#: are within half a step of the truth; the rest is room for the fit)
MISFIT_STEPS = 0.6
#: positions within this share of a quantum of the grid count as on it (float32 readings, a rounded offset)
GRID_TOLERANCE = 0.02


def encoder_quantum(positions_rad: ArrayLike) -> float:
    """The encoder's step [rad] when the positions (J,) lie on a grid, the smallest step between samples, all of
    them within GRID_TOLERANCE of a step from the first; 0 when they do not (readings that are not counts)."""
    q = np.asarray(positions_rad, dtype=float)
    steps = np.abs(np.diff(q))
    steps = steps[steps > 1e-12]
    if steps.size == 0:
        return 0.0
    quantum = float(steps.min())
    k = (q - q[0]) / quantum
    return quantum if bool(np.all(np.abs(k - np.round(k)) <= GRID_TOLERANCE)) else 0.0


def dequantised(stamps_s: ArrayLike, positions_rad: ArrayLike) -> FloatArray:
    """The joint positions (J,) freed of most of the encoder's quantisation, where the motion is smooth.

    An encoder reports the angle rounded to its step (2 pi / 4096 for a Dynamixel MX or XM: 0.088 deg); at the speed
    of a sweep that rounding error drifts through the step every few samples, the same for all beams of a scan, and
    the interpolated motor angle carries it (on a 2 mm scanner it was the largest error of b, and the per-scan
    covariance counted it for a and beta too: docs/study.md). Each sample is replaced by a quadratic in time fitted
    to the 2 DEQUANTISE_HALF_WINDOW + 1 samples about it (a trapezoidal sweep is piecewise quadratic), clipped to the
    sample's own step (the truth is within half a step of the reading). The readings are kept where the fitted motion
    turns within its window (a reversal, a start from or a stop to a standstill: a fit across the kink would add a
    turn the servo did not make), where the fit leaves a sample of its window more than MISFIT_STEPS steps away (a
    reversal under backlash, a sparse or jerky stream), and where the positions are not on a grid
    (:func:`encoder_quantum`). stamps_s (J,) increasing; the positions are returned unwrapped (a wrapping encoder's
    +-2 pi jumps removed)."""
    t = np.asarray(stamps_s, dtype=float)
    q = np.unwrap(np.asarray(positions_rad, dtype=float))
    K = DEQUANTISE_HALF_WINDOW
    quantum = encoder_quantum(q)
    if quantum == 0.0 or q.size < 2 * K + 1:
        return q.copy()
    start = np.clip(np.arange(q.size) - K, 0, q.size - 2 * K - 1)  # each sample's window, shifted inside at the ends
    idx = start[:, None] + np.arange(2 * K + 1)
    span = np.maximum(t[idx[:, -1]] - t[idx[:, 0]], 1e-12)[:, None]
    x = (t[idx] - t[:, None]) / span  # the window's times about the sample's, scaled to ~1
    X = np.stack([np.ones_like(x), x, x * x], axis=2)  # (J, 2K + 1, 3)
    A = np.einsum("jki,jkl->jil", X, X)
    solvable = np.abs(np.linalg.det(A)) > 1e-9  # a window of fewer than 3 distinct times (a burst) has no quadratic
    A[~solvable] = np.eye(3)
    coef = np.linalg.solve(A, np.einsum("jki,jk->ji", X, q[idx])[..., None])[..., 0]
    misfit = np.where(solvable, np.abs(np.einsum("jki,ji->jk", X, coef) - q[idx]).max(axis=1), np.inf)
    with np.errstate(divide="ignore", invalid="ignore"):
        vertex = -coef[:, 1] / (2.0 * coef[:, 2])  # where the fitted motion turns (a standstill, a reversal)
    turns = (vertex > x[:, 0]) & (vertex < x[:, -1])
    fit = np.clip(coef[:, 0], q - quantum / 2, q + quantum / 2)
    return np.where((misfit <= MISFIT_STEPS * quantum) & ~turns, fit, q)


__all__ = ["CLOCK_OFFSET_PASS_SHARE", "DEQUANTISE_HALF_WINDOW", "EDGE_WINDOW_S", "GAP_PERIODS", "MAX_CLOCK_OFFSET_S",
           "NO_CLOCK", "STEADY_SHARE", "TOP_PERCENTILE", "Clock", "JointGap", "JointSamples", "MotorAngles",
           "MotorClock",
           "clock_offset_bound_s", "dequantised", "encoder_quantum", "joint_gaps", "motor_angles"]
