"""Session calibration pipeline: store frames -> calibration/ functions -> stored results.

Work in progress (skeleton): ``calibrate_session`` runs every calibration stage that a
session's captures allow and records each result with provenance.
"""

from __future__ import annotations

from dataclasses import dataclass, field

__all__ = ["StageResult", "CalibrationReport", "calibrate_session"]


@dataclass
class StageResult:
    """Outcome of one calibration stage (status is 'ok', 'skipped' or 'failed')."""

    stage: str
    status: str
    reason: str = ""
    figures: dict = field(default_factory=dict)
    calibration_id: int | None = None


@dataclass
class CalibrationReport:
    """All stage outcomes of one ``calibrate_session`` run."""

    session: str
    stages: list[StageResult] = field(default_factory=list)


def calibrate_session(store, session_name, *, progress=None) -> CalibrationReport:
    """Run every calibration the session's captures allow (skeleton)."""
    raise NotImplementedError("calibrate_session is being written")
