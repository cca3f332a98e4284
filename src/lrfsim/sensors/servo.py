"""The servo: the motor trajectory lambda(t) and the joint-state stream it publishes.

Clocks. The simulation's true time is the servo's clock: t = 0 is the start of the trajectory. The laser stamps
the same instant as ``t + clock_offset_s`` (ServoConfig.clock_offset_s; laser stamp = servo stamp + offset),
see :func:`laser_time`.

Trajectory (``mode``, :func:`servo_trajectory`). ``sweep`` (:func:`sweep_trajectory`): ``settle_s``
standstill, then ``passes`` sweeps alternating start -> end -> start ..., each followed by ``settle_s``
standstill. ``spin`` (:func:`spin_trajectory`, a continuously turning motor): ``settle_s`` standstill at
``start_rad``, one move of ``revolutions`` full turns in ``spin_direction`` (the ramps included: it stops at
start_rad + spin_direction 2 pi revolutions), ``settle_s`` standstill; ``end_rad`` is not used. Each move is a
trapezoidal velocity profile: constant acceleration ``accel_rad_s2`` up to ``speed_rad_s``, cruise, symmetric
deceleration (a triangle when the move is too short to reach the speed). Position is C1, velocity is
continuous, acceleration piecewise constant. Angles are never wrapped: a spin's angle runs monotonically beyond
+-pi, as a ROS continuous joint publishes it.

``step`` (:func:`step_trajectory`, step and scan: a stepper tilt stand such as the URG-04LX stand of
github.com/liangfok/tilting_lidar_scanner, whose node commands one step, then takes the next scan stamped after
it): ``settle_s`` standstill, then ``passes`` passes alternating start -> end -> start ..., each of
|end - start| / ``step_rad`` steps, one every ``step_period_s``: a trapezoidal move of ``step_rad`` and a
standstill for the rest of the period; ``settle_s`` standstill after each pass. The laser is timed to the steps
(:func:`step_scan_phase_s`): one scan per step, centred in the step's standstill, so every beam of a scan sees the
same motor angle.

Joint states. Samples every ``1 / rate_hz`` from t = 0 to the end of the trajectory, stamped with the servo
clock; with ``mode: step`` one sample per scan instead, stamped with the scan's start (the angle the stand reports
with each scan). The reported position is the true angle passed through a backlash (play) operator of width
``backlash_rad`` and then quantised to the encoder's grid ``2 pi / encoder_counts`` (Dynamixel MX/XM: 4096
counts per revolution and 0.25-0.33 deg backlash: ROBOTIS e-Manual, emanual.robotis.com, MX-28 and XM430
pages). Velocity is the true velocity (not quantised).

Backlash model (the play operator, Krasnosel'skii-Pokrovskii): the reported angle r(t) stays inside the band
[lambda(t) - backlash/2, lambda(t) + backlash/2] and moves only when the band pushes it:

    r(t) = max(r_0, lambda(t) - backlash/2)  while lambda increases,
    r(t) = min(r_0, lambda(t) + backlash/2)  while lambda decreases,

with r_0 its value when the current motion began. In steady motion the report therefore lags the truth by
backlash/2 in the direction of motion; after a reversal it holds still until the truth has moved ``backlash``
back. Initial state: r = lambda(0) - s_1 backlash/2 with s_1 the direction of the first sweep (the servo
approached the start position moving that way, as after a homing move).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import ArrayLike, NDArray

from lrfcal.errors import InputError
from lrfsim.scenario.servo_timing import move_profile, step_move_s, steps_per_pass

if TYPE_CHECKING:  # annotations only
    from lrfsim.scenario.sections import SensorConfig, ServoConfig

FloatArray = NDArray[np.float64]

#: Trajectory.angle takes this many times at once (a block's temporaries, 256 KiB each, stay in the cache)
ANGLE_BLOCK = 32768


@dataclass(frozen=True)
class Trajectory:
    """A piecewise motion: K segments (holds and trapezoidal moves), back to back from t = 0.

    All arrays (K,): start_s segment start time; duration_s; from_rad start angle; direction (+1, -1, or 0 for a
    hold); distance_rad (>= 0); accel_rad_s2 (0 for a hold); ramp_s acceleration time; peak_rad_s cruise speed.
    """

    start_s: FloatArray
    duration_s: FloatArray
    from_rad: FloatArray
    direction: FloatArray
    distance_rad: FloatArray
    accel_rad_s2: FloatArray
    ramp_s: FloatArray
    peak_rad_s: FloatArray
    backlash_rad: float = 0.0

    @property
    def end_s(self) -> float:
        """Total duration [s]."""
        return float(self.start_s[-1] + self.duration_s[-1])

    def _locate(self, t_s: ArrayLike) -> tuple[NDArray[np.intp], FloatArray]:
        t = np.clip(np.asarray(t_s, dtype=float), 0.0, self.end_s)
        k = np.searchsorted(self.start_s, t, side="right") - 1
        k = np.clip(k, 0, self.start_s.size - 1)
        return k, t - self.start_s[k]

    def _phases(self, k: NDArray[np.intp], tau: FloatArray) -> tuple[FloatArray, FloatArray, NDArray[np.bool_],
                                                                         NDArray[np.bool_]]:
        """Into segment k: the local time tau clamped to its duration, the time left, and whether it is accelerating
        or (and not) decelerating."""
        tau = np.minimum(tau, self.duration_s[k])
        rem = self.duration_s[k] - tau
        ta = self.ramp_s[k]
        accel = tau < ta
        decel = rem < ta
        decel &= ~accel
        return tau, rem, accel, decel

    def _distance(self, k: NDArray[np.intp], tau: FloatArray) -> FloatArray:
        """Distance travelled (>= 0) into segment k at local time tau: a / 2 tau^2 accelerating, a / 2 ta^2 +
        vp (tau - ta) cruising, D - a / 2 rem^2 decelerating (the per-segment constants computed once, the
        per-time work in place: this runs on every beam of a simulation)."""
        tau, rem, accel, decel = self._phases(k, tau)
        half_a = (0.5 * self.accel_rad_s2)[k]
        s = tau - self.ramp_s[k]
        s *= self.peak_rad_s[k]
        s += (0.5 * self.accel_rad_s2 * self.ramp_s**2)[k]
        np.copyto(s, half_a * tau**2, where=accel)
        np.copyto(s, self.distance_rad[k] - half_a * rem**2, where=decel)
        return s

    def angle(self, t_s: ArrayLike) -> FloatArray:
        """True motor angle lambda(t) [rad], same shape as ``t_s`` (servo clock; clamped to [0, end]). Many times
        (every beam of a recording) are taken in blocks of ANGLE_BLOCK, whose temporaries stay in the cache: the
        same numbers, 1.2-4x faster (the more so on a machine whose memory other work keeps busy)."""
        t = np.asarray(t_s, dtype=float)
        if t.size <= ANGLE_BLOCK:
            k, tau = self._locate(t)
            return self.from_rad[k] + self.direction[k] * self._distance(k, tau)
        flat = t.reshape(-1)
        out = np.empty(flat.size)
        for i in range(0, flat.size, ANGLE_BLOCK):
            out[i:i + ANGLE_BLOCK] = self.angle(flat[i:i + ANGLE_BLOCK])
        return out.reshape(t.shape)

    def velocity(self, t_s: ArrayLike) -> FloatArray:
        """True motor velocity d lambda / dt [rad/s], same shape as ``t_s``: a tau, vp, a rem by phase."""
        k, tau = self._locate(t_s)
        tau, rem, accel, decel = self._phases(k, tau)
        a = self.accel_rad_s2[k]
        v = np.where(accel, a * tau, np.where(decel, a * rem, self.peak_rad_s[k]))
        return self.direction[k] * v

    def reported_angle(self, t_s: ArrayLike) -> FloatArray:
        """The angle after the backlash play operator (module docstring), before encoder quantisation."""
        lam = self.angle(t_s)
        h = 0.5 * self.backlash_rad
        if h == 0.0:
            return lam
        # state r_0 at the start of every segment, propagated segment by segment (K is small)
        moves = self.direction != 0
        first = float(self.direction[moves][0]) if moves.any() else 1.0
        r0 = np.empty(self.start_s.size)
        r = float(self.from_rad[0]) - first * h
        for j in range(self.start_s.size):
            r0[j] = r
            end = float(self.from_rad[j] + self.direction[j] * self.distance_rad[j])
            if self.direction[j] > 0:
                r = max(r, end - h)
            elif self.direction[j] < 0:
                r = min(r, end + h)
        k, _ = self._locate(t_s)
        d = self.direction[k]
        out = np.where(d > 0, np.maximum(r0[k], lam - h), r0[k])
        return np.where(d < 0, np.minimum(r0[k], lam + h), out)


#: one row of a trajectory: (duration_s, from_rad, direction, distance_rad, accel_rad_s2, ramp_s, peak_rad_s)
_Row = tuple[float, float, float, float, float, float, float]


def _hold(duration_s: float, at_rad: float) -> _Row:
    return (duration_s, at_rad, 0.0, 0.0, 0.0, 0.0, 0.0)


def _move(from_rad: float, direction: float, distance_rad: float, servo: ServoConfig) -> _Row:
    T, ramp, peak = move_profile(distance_rad, servo.speed_rad_s, servo.accel_rad_s2)
    return (T, from_rad, direction, distance_rad, servo.accel_rad_s2, ramp, peak)


def _trajectory(rows: list[_Row], backlash_rad: float) -> Trajectory:
    arr = np.array(rows, dtype=float)
    starts = np.concatenate([[0.0], np.cumsum(arr[:-1, 0])])
    return Trajectory(start_s=starts, duration_s=arr[:, 0], from_rad=arr[:, 1], direction=arr[:, 2],
                      distance_rad=arr[:, 3], accel_rad_s2=arr[:, 4], ramp_s=arr[:, 5], peak_rad_s=arr[:, 6],
                      backlash_rad=backlash_rad)


def step_trajectory(servo: ServoConfig) -> Trajectory:
    """The step and scan of a scenario (mode step): hold, then per pass (move of step_rad, hold for the rest of
    step_period_s) x steps_per_pass and a hold of settle_s (module docstring)."""
    if servo.mode != "step":
        raise ValueError(f"step_trajectory: servo.mode is {servo.mode!r} (use servo_trajectory)")
    sign = math.copysign(1.0, servo.end_rad - servo.start_rad)
    n = steps_per_pass(servo)
    move = _move(0.0, 0.0, servo.step_rad, servo)
    rest = servo.step_period_s - move[0]
    rows = [_hold(servo.settle_s, servo.start_rad)]
    for p in range(servo.passes):
        d = sign if p % 2 == 0 else -sign
        at = servo.start_rad if p % 2 == 0 else servo.end_rad
        for k in range(n):
            here = at + d * k * servo.step_rad
            rows += [(move[0], here, d, *move[3:]), _hold(rest, here + d * servo.step_rad)]
        rows.append(_hold(servo.settle_s, servo.end_rad if p % 2 == 0 else servo.start_rad))
    return _trajectory(rows, servo.backlash_rad)


def step_scan_phase_s(servo: ServoConfig, sensor: SensorConfig) -> float:
    """Mode step: the laser's phase [s] (lrfsim.sensors.lidar.scan_start_times) that centres every scan's beams in a
    step's standstill: the steps start at settle_s + k step_period_s (settle_s a whole number of periods), each
    standstill begins when the step's move ends, and the beams take (n_beams - 1) time_increment_s of it."""
    move = step_move_s(servo)
    beams = (sensor.n_beams - 1) * sensor.time_increment_s
    slack = servo.step_period_s - move - beams
    return math.fmod(servo.settle_s + move + 0.5 * slack, servo.step_period_s)


def sweep_trajectory(servo: ServoConfig) -> Trajectory:
    """The sweep of a scenario: hold, (move, hold) x passes (module docstring). A spin is
    :func:`spin_trajectory`, a step and scan :func:`step_trajectory`; :func:`servo_trajectory` picks by
    ``servo.mode``."""
    if servo.mode != "sweep":
        raise ValueError(f"sweep_trajectory: servo.mode is {servo.mode!r} (use servo_trajectory)")
    dist = abs(servo.end_rad - servo.start_rad)
    sign = math.copysign(1.0, servo.end_rad - servo.start_rad)
    rows = [_hold(servo.settle_s, servo.start_rad)]
    at = servo.start_rad
    for p in range(servo.passes):
        rows.append(_move(at, sign if p % 2 == 0 else -sign, dist, servo))
        at = servo.end_rad if p % 2 == 0 else servo.start_rad
        rows.append(_hold(servo.settle_s, at))
    return _trajectory(rows, servo.backlash_rad)


def spin_trajectory(servo: ServoConfig) -> Trajectory:
    """The spin of a scenario: hold at start_rad, one move of 2 pi revolutions in spin_direction (ramps
    included), hold (module docstring)."""
    rows = [_hold(servo.settle_s, servo.start_rad),
            _move(servo.start_rad, float(servo.spin_direction), 2.0 * math.pi * servo.revolutions, servo),
            _hold(servo.settle_s, _spin_stop_rad(servo))]
    return _trajectory(rows, servo.backlash_rad)


def _spin_stop_rad(servo: ServoConfig) -> float:
    """Where a spin stops: start_rad + spin_direction 2 pi revolutions (unwrapped)."""
    return servo.start_rad + servo.spin_direction * 2.0 * math.pi * servo.revolutions


def servo_trajectory(servo: ServoConfig) -> Trajectory:
    """The scenario's motor trajectory: :func:`sweep_trajectory`, :func:`spin_trajectory` or :func:`step_trajectory`
    by ``servo.mode``."""
    if servo.mode == "spin":
        return spin_trajectory(servo)
    return step_trajectory(servo) if servo.mode == "step" else sweep_trajectory(servo)


def covered_angles_rad(servo: ServoConfig) -> tuple[float, float]:
    """(lo, hi), lo < hi: the motor angles [rad] the trajectory passes through (unwrapped): a sweep's (or step and
    scan's) start and end, sorted; a spin's start_rad and where it stops (hi - lo = 2 pi revolutions, more than a
    turn when it turns more than once)."""
    end = _spin_stop_rad(servo) if servo.mode == "spin" else servo.end_rad
    return min(servo.start_rad, end), max(servo.start_rad, end)


def quantise_encoder(angle_rad: ArrayLike, encoder_counts: int) -> FloatArray:
    """Round to the encoder grid 2 pi / counts (0 counts: unchanged). Same shape as ``angle_rad``."""
    a = np.asarray(angle_rad, dtype=float)
    if encoder_counts == 0:
        return a.copy()
    step = 2.0 * math.pi / encoder_counts
    return np.round(a / step) * step


@dataclass(frozen=True)
class JointSamples:
    """The servo's JointState stream: stamps_s (J,) servo clock, positions_rad (J,) reported (backlash +
    encoder), velocities_rad_s (J,) true velocity, true_positions_rad (J,) the truth at the stamps."""

    stamps_s: FloatArray
    positions_rad: FloatArray
    velocities_rad_s: FloatArray
    true_positions_rad: FloatArray


def joint_samples(traj: Trajectory, servo: ServoConfig, scan_starts_s: FloatArray | None = None) -> JointSamples:
    """Samples at k / rate_hz, k = 0 .. floor(end * rate_hz), on the servo clock; with ``mode: step`` one sample at
    each scan's start ``scan_starts_s`` (S,) (servo clock; required then) instead."""
    if servo.mode == "step":
        if scan_starts_s is None:
            raise ValueError("joint_samples: mode step publishes one joint state per scan: give scan_starts_s")
        t = np.asarray(scan_starts_s, dtype=float).copy()
    else:
        n = int(math.floor(traj.end_s * servo.rate_hz + 1e-9)) + 1
        t = np.arange(n, dtype=float) / servo.rate_hz
    return JointSamples(
        stamps_s=t,
        positions_rad=quantise_encoder(traj.reported_angle(t), servo.encoder_counts),
        velocities_rad_s=traj.velocity(t),
        true_positions_rad=traj.angle(t),
    )


def laser_time(t_servo_s: ArrayLike, clock_offset_s: float) -> FloatArray:
    """Laser-clock stamp of the instant the servo clock reads ``t_servo_s``: t + clock_offset_s."""
    return np.asarray(t_servo_s, dtype=float) + clock_offset_s


def check_trajectory(traj: Trajectory, max_duration_s: float = 3600.0) -> None:
    """Refuse absurd recordings (hours of data) before allocating them."""
    if traj.end_s > max_duration_s:
        raise InputError(f"servo: the motion lasts {traj.end_s:.0f} s, more than {max_duration_s:.0f} s")


__all__ = ["JointSamples", "Trajectory", "check_trajectory", "covered_angles_rad", "joint_samples", "laser_time",
           "move_profile", "quantise_encoder", "servo_trajectory", "spin_trajectory", "step_scan_phase_s",
           "step_trajectory", "sweep_trajectory"]
