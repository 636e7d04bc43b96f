"""The one way the calibration fits run ``scipy.optimize.least_squares``: a fit that stops
without converging raises :class:`~calibration.errors.NotConverged` instead of returning its
last iterate as if it were a solution."""
from __future__ import annotations

from scipy.optimize import OptimizeResult, least_squares

from .errors import NotConverged


def solve(residuals, x0, *, what: str, max_evaluations: int | None = None, **options) -> OptimizeResult:
    """``least_squares(residuals, x0, max_nfev=max_evaluations, **options)``, checked.

    Parameters
    ----------
    residuals : callable(x) -> ndarray of shape (M,)
    x0 : ndarray of shape (P,)
    what : str
        The fit's name for the error message, e.g. ``'turntable bundle adjustment'``.
    max_evaluations : int, optional
        Residual evaluations allowed (scipy's default when None).

    Raises
    ------
    NotConverged
        scipy's status is 0 (evaluation budget spent) or negative (improper input).
    """
    sol = least_squares(residuals, x0, max_nfev=max_evaluations, **options)
    if sol.status <= 0:
        raise NotConverged(what, status=int(sol.status), solver_message=str(sol.message))
    return sol
