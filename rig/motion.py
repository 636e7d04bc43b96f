"""Motion-time model shared by the drivers (move timeouts) and the planner (time estimates)."""
from __future__ import annotations

import math


def move_time_s(distance: float, speed: float, accel: float) -> float:
    """Duration of a rest-to-rest trapezoidal (or, when too short to reach ``speed``,
    triangular) move, seconds.

    Parameters
    ----------
    distance : float
        Travel in any length unit (degrees, millimetres, microsteps); its sign is ignored.
    speed, accel : float
        Top speed (unit/s) and acceleration (unit/s^2), both > 0.
    """
    if not (speed > 0 and accel > 0):
        raise ValueError(f"speed and accel must be > 0 (got {speed}, {accel})")
    distance = abs(distance)
    if distance <= speed * speed / accel:  # never reaches top speed
        return 2.0 * math.sqrt(distance / accel)
    return distance / speed + speed / accel
