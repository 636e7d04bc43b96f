"""Typed calibration errors.

``calibration`` is pure and imports nothing of ours, so its errors live here rather than in
``rig.errors``. Each one says what was wrong and where (frame name, argument, view index), so a
caller can show it to an operator as is.
"""
from __future__ import annotations


class CalibrationError(ValueError):
    """Base of all calibration failures (a ``ValueError``: the input could not be calibrated)."""


class TargetNotFound(CalibrationError):
    """No calibration target (board, sphere, highlight) could be found in a frame."""

    def __init__(self, message: str, *, frame: str | None = None) -> None:
        self.frame = frame
        super().__init__(f"{frame}: {message}" if frame else message)


class TooFewViews(CalibrationError):
    """Fewer usable views (or samples) than the fit needs."""

    def __init__(self, message: str, *, have: int, need: int) -> None:
        self.have = have
        self.need = need
        super().__init__(f"{message} (have {have}, need at least {need})")


class DegenerateFit(CalibrationError):
    """The data cannot determine the parameters (parallel views, collinear points, no spread)."""


class InvalidInput(CalibrationError):
    """An argument is unusable before any fitting starts (wrong shape, type or range, NaN/inf).

    The message names the argument (``argument`` holds its name when the caller gave it).
    """

    def __init__(self, message: str, *, argument: str | None = None) -> None:
        self.argument = argument
        super().__init__(message)


class NotConverged(CalibrationError):
    """An iterative fit stopped without meeting its convergence tolerances.

    ``status`` and ``message`` are the solver's (``scipy.optimize.least_squares``).
    """

    def __init__(self, message: str, *, status: int, solver_message: str) -> None:
        self.status = status
        self.solver_message = solver_message
        super().__init__(f"{message} did not converge (status {status}: {solver_message})")
