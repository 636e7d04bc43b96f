"""Motion-time model shared by the drivers (move timeouts) and the planner (time estimates):
:func:`motionprofile.trapezoid_duration`, the one formula the simulators use too."""
from __future__ import annotations

from motionprofile import trapezoid_duration as move_time_s

__all__ = ["move_time_s"]
