"""The plan as the report shows it: one row per kind of step, its angles as compact ranges.

:func:`plan_rows` reads a session's expanded steps (:meth:`capture.store.Store.steps`, dicts of
:meth:`capture.plan.Step.to_dict`) and stored frames, and groups the steps by kind (held-out
measurements apart): the turntable angles, the lamp positions, the polarizer states and the
exposures each kind visits, with its frames and bytes. :func:`compact_angles` writes a set of
angles as runs (``0–270 by 90 (4)``), unwrapping the turntable's circle so that a sweep through
0° (300, 310, ..., 60) is one run.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Sequence

import numpy as np

from rig import LightTarget

from ..plan import Step
from ..store import FrameRecord

__all__ = ["PlanRow", "compact_angles", "plan_rows"]


@dataclass(frozen=True)
class PlanRow:
    """One kind of step of a session's plan.

    ``turntable``, ``lights``, ``polarizer`` are compact angle lists in degrees (lab frame;
    lights as azimuth x elevation about the turntable axis), ``exposures`` in milliseconds, ``–``
    where the steps leave the axis alone; ``frames_planned`` / ``frames_stored`` count frames,
    ``bytes_stored`` is the stored frames' size in bytes."""

    kind: str
    steps: int
    turntable: str
    lights: str
    polarizer: str
    exposures: str
    frames_planned: int
    frames_stored: int
    bytes_stored: int


def compact_angles(values: Sequence[float], *, period: float | None = None) -> str:
    """Angles (deg) as sorted runs: three or more evenly spaced become ``first–last by step (n)``,
    the rest are listed. With ``period`` (360 for the turntable) angles are taken modulo it and
    the list starts after its widest gap, so a sweep through 0° stays one run. ``–`` when empty."""
    v = np.unique(np.round(np.asarray(values, float), 6))
    if v.size == 0:
        return "–"
    if period is not None and v.size > 1:
        v = np.unique(np.round(np.mod(v, period), 6))
        gaps = np.diff(np.append(v, v[0] + period))
        start = (int(np.flatnonzero(np.isclose(gaps, gaps.max()))[-1]) + 1) % v.size   # ties: from the lowest
        v = np.concatenate([v[start:], v[:start] + period])   # increasing, unwrapped
    shown = (lambda x: np.mod(x, period)) if period is not None else (lambda x: x)
    d = np.diff(v)
    parts, i = [], 0
    while i < v.size:
        j = i + 1   # v[i..j] is a run of step d[i] = v[i + 1] - v[i] while d[j] matches it
        while j + 1 < v.size and np.isclose(d[j], d[i]):
            j += 1
        if j - i >= 2:
            parts.append(f"{shown(v[i]):g}–{shown(v[j]):g} by {d[i]:g} ({j - i + 1})")
            i = j + 1
        else:
            parts.append(f"{shown(v[i]):g}")
            i += 1
    return ", ".join(parts)


def _lights(lights: list[LightTarget]) -> str:
    """Lamp positions: ``az A × el E`` when they are the full grid of their azimuths and
    elevations, else their count and both lists; ``–`` when the steps leave the lamp alone."""
    if not lights:
        return "–"
    pairs = {(round(lt.azimuth_deg, 6), round(lt.elevation_deg, 6)) for lt in lights if lt.xyz_mm is None}
    text = ""
    if pairs:
        az, el = sorted({a for a, _ in pairs}), sorted({e for _, e in pairs})
        text = (f"az {compact_angles(az)} × el {compact_angles(el)}" if len(pairs) == len(az) * len(el)
                else f"{len(pairs)} positions (az {compact_angles(az)}; el {compact_angles(el)})")
    xyz = len({lt.xyz_mm for lt in lights if lt.xyz_mm is not None})
    return ", ".join(filter(None, (text, f"{xyz} at x, y, z (mm)" if xyz else "")))


def _exposures_ms(exposures: list[float]) -> str:
    ms = np.unique(np.round(np.asarray(exposures, float) * 1e3, 6))
    if ms.size == 0:
        return "–"
    if ms.size > 4:
        return f"{ms[0]:g}–{ms[-1]:g} ms ({ms.size})"
    return ", ".join(f"{x:g}" for x in ms) + " ms"


def plan_rows(steps: Sequence[Step], frames: Sequence[FrameRecord]) -> list[PlanRow]:
    """The session's steps grouped by kind (held-out measurements a kind of their own), in the
    order the session first reaches each kind.

    Parameters
    ----------
    steps : sequence of Step
        The session's steps (:attr:`capture.store.StoredStep.step`).
    frames : sequence of FrameRecord
        The session's stored frames (their ``step`` and ``size``).
    """
    if not steps:
        return []
    index = np.array([s.index for s in steps])
    n = int(index.max()) + 1
    f_step = np.array([f.step for f in frames], dtype=int)
    count = np.bincount(f_step, minlength=n)
    size = np.bincount(f_step, weights=np.array([f.size for f in frames], float), minlength=n)
    groups: dict[str, list[Step]] = {}
    for s in sorted(steps, key=lambda s: s.index):
        groups.setdefault(s.kind + (" (held out)" if s.held_out else ""), []).append(s)
    rows = []
    for kind, group in groups.items():
        ids = np.array([s.index for s in group])
        rows.append(PlanRow(
            kind=kind, steps=len(group),
            turntable=compact_angles([s.turntable_deg for s in group if s.turntable_deg is not None],
                                     period=360.0),
            lights=_lights([s.light for s in group if s.light is not None]),
            polarizer=compact_angles([s.polarizer_deg for s in group if s.polarizer_deg is not None]),
            exposures=_exposures_ms([e for s in group for e in s.exposures_s]),
            frames_planned=int(sum(s.frames for s in group)),
            frames_stored=int(count[ids].sum()), bytes_stored=int(size[ids].sum())))
    return rows
