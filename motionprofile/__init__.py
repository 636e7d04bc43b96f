"""The rest-to-rest trapezoidal motion profile: duration, distance and speed over time.

One formula for the drivers' move timeouts and the planner's estimates (``rig.motion``) and for
the firmware simulators' motion (``sims``). Dependency-free and importing nothing of gonio, so
both ``rig`` (which imports nothing else of ours) and ``sims`` may import it.
"""
from __future__ import annotations

import math

__all__ = ["trapezoid_distance", "trapezoid_duration", "trapezoid_speed"]


def trapezoid_duration(distance: float, vmax: float, amax: float) -> float:
    """Duration of a rest-to-rest trapezoidal (or, when too short to reach ``vmax``,
    triangular) move, seconds.

    Parameters
    ----------
    distance : float
        Travel in any length unit (degrees, millimetres, microsteps); its sign is ignored.
    vmax, amax : float
        Top speed (unit/s) and acceleration (unit/s^2), both > 0.
    """
    if not (vmax > 0 and amax > 0):
        raise ValueError(f"speed and accel must be > 0 (got {vmax}, {amax})")
    distance = abs(distance)
    if distance <= vmax * vmax / amax:  # never reaches top speed
        return 2.0 * math.sqrt(distance / amax)
    return vmax / amax + distance / vmax


def trapezoid_distance(distance: float, vmax: float, amax: float, t: float) -> float:
    """Distance covered after ``t`` seconds of a rest-to-rest trapezoidal move.

    Parameters
    ----------
    distance : float
        Total (unsigned) distance of the move.
    vmax, amax : float
        Speed and acceleration limits in the same length unit per s and per s^2.
    t : float
        Time since the start of the move, seconds (clipped to the move's duration).
    """
    distance = abs(distance)
    total = trapezoid_duration(distance, vmax, amax)
    if t >= total:
        return distance
    if t <= 0.0:
        return 0.0
    t_acc = min(vmax / amax, total / 2.0)
    v_peak = amax * t_acc
    if t < t_acc:
        return 0.5 * amax * t * t
    if t > total - t_acc:
        rest = total - t
        return distance - 0.5 * amax * rest * rest
    return 0.5 * amax * t_acc * t_acc + v_peak * (t - t_acc)


def trapezoid_speed(distance: float, vmax: float, amax: float, t: float) -> float:
    """Speed (length unit per s) ``t`` seconds into a rest-to-rest trapezoidal move."""
    total = trapezoid_duration(distance, vmax, amax)
    if t <= 0.0 or t >= total:
        return 0.0
    return amax * min(t, vmax / amax, total - t)
