"""Typed rows the store returns."""
from __future__ import annotations

from dataclasses import dataclass, field
from functools import cached_property
from typing import Any

from ..plan import Step


@dataclass(frozen=True)
class SessionInfo:
    """One session row. ``plan`` is the canonical plan dict; times are Unix seconds."""

    id: int
    name: str
    state: str
    operator: str
    object: str
    notes: str
    plan: dict[str, Any]
    plan_hash: str
    plan_path: str | None
    created: float
    updated: float


@dataclass(frozen=True)
class StoredStep:
    """One stored step: its ``index`` in execution order, ``spec`` the JSON it was stored as and
    whether it is ``done``. :attr:`step` is the capture plan's :class:`capture.plan.Step` (a
    session imported from elsewhere stores steps of its own, read through ``spec``)."""

    index: int
    spec: dict[str, Any]
    done: bool

    @cached_property
    def step(self) -> Step:
        """The plan step (``ValueError`` naming the step when ``spec`` is not one)."""
        try:
            return Step.from_dict(self.spec)
        except (KeyError, TypeError, ValueError) as exc:
            raise ValueError(f"stored step {self.index} is not a capture plan's step ({type(exc).__name__}: "
                             f"{exc}); its kind is {self.spec.get('kind')!r}") from None


@dataclass(frozen=True)
class FrameRecord:
    """One stored frame. Exposures in seconds; ``positions`` are read-backs (degrees, mm)."""

    id: int
    session_id: int
    step: int
    bracket_index: int
    repeat: int
    sha256: str
    size: int
    filename: str
    format: str
    exposure_requested_s: float | None
    exposure_s: float | None
    iso: float | None
    fnumber: float | None
    positions: dict[str, Any]
    captured_at: float
    stored_at: float
    metadata: dict[str, Any]


@dataclass(frozen=True)
class ResultRecord:
    """One stored calibration or reconstruction result with its provenance.

    ``category`` ``calibration`` or ``reconstruction``; ``kind`` what it is (``intrinsics``,
    ``lensch`` ...); ``result`` / ``params`` the JSON the computation stored; ``input_frames``
    the frame ids it used; ``artifacts`` name -> SHA-256 of its stored objects (read with
    :meth:`~capture.store.Store.read_object`); ``created`` Unix seconds."""

    id: int
    category: str
    kind: str
    created: float
    params: dict[str, Any]
    result: dict[str, Any]
    input_frames: list[int]
    code_version: str
    artifacts: dict[str, str]


@dataclass(frozen=True)
class Progress:
    """Counts of a session: planned and done steps, planned frames, stored frames and bytes."""

    steps_total: int
    steps_done: int
    frames_total: int
    frames_stored: int
    bytes_stored: int


@dataclass
class VerifyReport:
    """Outcome of :meth:`Store.verify`: lists of SHA-256 names / paths, empty when all is well."""

    checked: int = 0
    missing: list[str] = field(default_factory=list)
    corrupt: list[str] = field(default_factory=list)
    orphans: list[str] = field(default_factory=list)
    incomplete_steps: list[int] = field(default_factory=list)
    #: sha256 -> where the session uses it (``step 3 frame 1 ...``, ``result dark #2 ...``)
    where: dict[str, list[str]] = field(default_factory=dict)
    #: False for a session recorded before journals (none written yet): were the database lost,
    #: its frames could not be put back (``rebuild-index`` or the next writer writes one)
    journaled: bool = True

    @property
    def ok(self) -> bool:
        return not (self.missing or self.corrupt or self.orphans or self.incomplete_steps)

