"""How long the servo section's motion takes: the trapezoidal move (pure arithmetic on a distance, a cruise speed
and an acceleration) and the run time of a whole sweep or spin, from the scenario's ``servo`` section alone.

lrfsim.sensors.servo builds the trajectory from these moves; lrfsim.scenario.file sizes a scenario (its memory estimate)
with :func:`servo_run_time_s`, which is therefore here, beside the scenario, and not in the servo model above it. The
run time is bit for bit the trajectory's ``end_s`` (the same durations, summed in the same order;
tests/test_servo.py).
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING

if TYPE_CHECKING:  # annotations only
    from .sections import ServoConfig


def move_profile(distance_rad: float, speed_rad_s: float, accel_rad_s2: float) -> tuple[float, float, float]:
    """Trapezoidal profile of a move: (duration_s, ramp_s, peak_rad_s).

    Cruise at ``speed`` if the move is long enough (distance >= speed^2 / accel): duration = D / v + v / a;
    otherwise a triangle: ramp = sqrt(D / a), peak = a * ramp, duration = 2 ramp.
    """
    if distance_rad <= 0:
        return 0.0, 0.0, 0.0
    ramp = speed_rad_s / accel_rad_s2
    if distance_rad >= speed_rad_s * ramp:
        return distance_rad / speed_rad_s + ramp, ramp, speed_rad_s
    ramp = math.sqrt(distance_rad / accel_rad_s2)
    return 2.0 * ramp, ramp, accel_rad_s2 * ramp


def steps_per_pass(servo: ServoConfig) -> int:
    """Mode step: the steps of one pass, |end_rad - start_rad| / step_rad (a whole number, ServoConfig checks)."""
    return int(round(abs(servo.end_rad - servo.start_rad) / servo.step_rad))


def step_move_s(servo: ServoConfig) -> float:
    """Mode step: the duration [s] of one step's move (a trapezoid or triangle of speed_rad_s, accel_rad_s2)."""
    return move_profile(servo.step_rad, servo.speed_rad_s, servo.accel_rad_s2)[0]


def servo_run_time_s(servo: ServoConfig) -> float:
    """The duration [s] of the servo's whole motion (lrfsim.sensors.servo.servo_trajectory(servo).end_s): a sweep is a
    hold, then ``passes`` times a move and a hold; a spin a hold, one move of ``revolutions`` turns and a hold; a step
    and scan a hold, then ``passes`` times (a step's move and the rest of its step period, per step) and a hold."""
    if servo.mode == "spin":
        move = move_profile(2.0 * math.pi * servo.revolutions, servo.speed_rad_s, servo.accel_rad_s2)[0]
        durations = [servo.settle_s, move, servo.settle_s]
    elif servo.mode == "step":
        move = step_move_s(servo)
        one_pass = [move, servo.step_period_s - move] * steps_per_pass(servo)
        durations = [servo.settle_s] + (one_pass + [servo.settle_s]) * servo.passes
    else:
        move = move_profile(abs(servo.end_rad - servo.start_rad), servo.speed_rad_s, servo.accel_rad_s2)[0]
        durations = [servo.settle_s] + [move, servo.settle_s] * servo.passes
    start = 0.0  # the last segment's start, summed one by one as the trajectory's cumulative sum does
    for d in durations[:-1]:
        start += d
    return start + durations[-1]


__all__ = ["move_profile", "servo_run_time_s", "step_move_s", "steps_per_pass"]
