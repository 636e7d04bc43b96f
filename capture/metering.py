"""Auto-exposure from metering shots: the raw histogram of the camera's own file.

A metering shot is decoded with :func:`calibration.raw.read_raw`; its visible CFA values are
normalised to the fraction of the usable range, ``(raw - black) / (white - black)`` with each
photosite's own channel black level. Raw values are linear in exposure time,
so the exposure that puts a chosen highlight percentile at a chosen level follows from one
unclipped shot. A shot with clipped highlights says only "too much": the exposure is cut by
``jump_stops`` and metered again; a shot with no signal above the noise floor is lengthened.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Callable

import numpy as np

from calibration.errors import InvalidInput
from calibration.raw import read_raw


class MeteringError(RuntimeError):
    """No exposure in the camera's range meters the scene (too dark or too bright)."""


def raw_signal(data: bytes) -> np.ndarray:
    """Visible raw values of a camera file as fractions of the usable range, float32, shape (H, W)
    (the CFA mosaic, not demosaiced): 0 at each photosite's own channel black level, 1 at the
    white level (:meth:`calibration.raw.RawMosaic.signal`)."""
    try:
        return read_raw(data, name="the metering shot").signal()
    except InvalidInput as exc:
        raise MeteringError(str(exc)) from None


@dataclass(frozen=True)
class Metering:
    """Result of :func:`meter`.

    Attributes
    ----------
    exposure_s : float
        Metered exposure, seconds: the ``percentile`` of the raw signal lands at ``highlight``.
    shots : list of dict
        Each metering shot: ``exposure_s``, ``percentile_value`` (fraction of range) and
        ``saturated_fraction`` (fraction of pixels at or above ``clip``).
    """

    exposure_s: float
    shots: list[dict[str, float]] = field(default_factory=list)


def meter(capture: Callable[[float], bytes], start_s: float, *, limits_s: tuple[float, float],
          highlight: float = 0.8, percentile: float = 99.5, clip: float = 0.95,
          max_saturated: float = 0.001, floor: float = 0.01, jump_stops: float = 4.0,
          max_shots: int = 6) -> Metering:
    """Find the exposure that puts the scene's highlights at ``highlight`` of the raw range.

    Parameters
    ----------
    capture : callable(exposure_s) -> bytes
        Takes one shot at that exposure (seconds) and returns the camera's raw file.
    start_s : float
        First metering exposure, seconds.
    limits_s : (float, float)
        The camera's exposure range, seconds; the result is clamped into it.
    highlight : float
        Target level of the ``percentile`` (fraction of the range between black and white).
    percentile : float
        Which percentile of the raw values counts as "the highlights", percent.
    clip, max_saturated : float
        A shot with more than ``max_saturated`` of its pixels at or above ``clip`` is clipped.
    floor : float
        A shot whose percentile lies below ``floor`` is too dark to meter.
    jump_stops : float
        Stops to shorten / lengthen after a clipped / too dark shot.
    max_shots : int
        Metering shots allowed.

    Raises
    ------
    MeteringError
        The scene stays clipped at the shortest or too dark at the longest exposure.
    """
    if not 0 < highlight < clip <= 1:
        raise ValueError(f"need 0 < highlight ({highlight}) < clip ({clip}) <= 1")
    lo, hi = limits_s
    t = float(np.clip(start_s, lo, hi))
    shots: list[dict[str, float]] = []
    for _ in range(max_shots):
        s = raw_signal(capture(t))
        p = float(np.percentile(s, percentile))
        sat = float(np.mean(s >= clip))
        shots.append({"exposure_s": t, "percentile_value": p, "saturated_fraction": sat})
        if sat > max_saturated:
            if t <= lo:
                raise MeteringError(f"{sat:.1%} of the pixels clip even at the shortest exposure "
                                    f"{lo:g} s: reduce the light or the ISO")
            t = max(lo, t / 2 ** jump_stops)
        elif p < floor:
            if t >= hi:
                raise MeteringError(f"too dark to meter even at the longest exposure {hi:g} s "
                                    f"({percentile:g}th percentile at {p:.3%} of the range)")
            t = min(hi, t * 2 ** jump_stops)
        else:
            return Metering(exposure_s=float(np.clip(t * highlight / p, lo, hi)), shots=shots)
    raise MeteringError(f"no usable metering shot in {max_shots} tries: {shots}")
