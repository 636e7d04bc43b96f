"""The one progress protocol of the pipeline: a typed :class:`Progress` event handed to a sink.

``gonio calibrate``, ``gonio process``, ``gonio demo`` and the console's processing all report
through it. ``stage`` is the top-level part (``capture``, ``calibration``, ``inputs``,
``lumitexels``, a method's name, ``report``), counted in ``done`` of ``total`` units (frames,
calibration stages, steps, samples: whatever the stage counts). Inside a calibration run ``part``
names the calibration stage and ``part_done`` / ``part_total`` count within it (HDR steps merged),
so nothing is encoded in a label.

The pure packages (``calibration``, ``reconstruct``) keep scipy's plain ``progress(done, total)``
callbacks; :func:`counter` adapts one into this protocol.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Callable


@dataclass(frozen=True)
class Progress:
    """Where a pipeline run is (see the module docstring)."""

    stage: str
    done: int
    total: int
    part: str = ""
    part_done: int | None = None
    part_total: int | None = None


#: where :class:`Progress` events go (a progress bar, the console); must not raise
ProgressSink = Callable[[Progress], None]


def counter(sink: ProgressSink | None, stage: str) -> Callable[[int, int], None] | None:
    """A ``(done, total)`` callback for the pure packages that reports ``stage`` to ``sink``
    (None when there is no sink, so the callee skips its counting)."""
    if sink is None:
        return None
    return lambda done, total: sink(Progress(stage, done, total))
