"""The trapezoidal move of a servo (lrfsim.servo builds the sweep from it; lrfsim.scenario sizes a scenario with
it): pure arithmetic on a distance, a cruise speed and an acceleration."""

from __future__ import annotations

import math


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


__all__ = ["move_profile"]
