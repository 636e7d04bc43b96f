"""Whether a session's stored calibration is complete and still matches its captures.

:func:`capture.pipeline.calibrate.calibrate_session` stores each stage as it finishes, so an
interrupted run (Ctrl-C, SIGKILL, a full disk) leaves some stages stored and others not, and a
capture resumed afterwards adds frames the stored stages never saw. A run of every stage ends by
storing one more calibration result, kind :data:`RUN_KIND`: each stage's status, reason and
result id, and a digest of the session's frames. A calibration is *complete* when the newest
calibration result is such a record (nothing stored after it: no later run was cut short) and its
frame digest is the session's current one; ``gonio process`` reuses only a complete calibration
and reads only the results that record lists, and otherwise runs the calibration again.
"""
from __future__ import annotations

import hashlib
from dataclasses import dataclass, field

from ..store import ResultRecord, Store
from .stage_records import RECORDS, CalibrationRun, StageRun, read_record

__all__ = ["RUN_KIND", "StoredCalibration", "frames_digest", "record_run", "stored_calibration"]

#: result kind of the record that closes a run of every calibration stage
RUN_KIND = CalibrationRun.KIND


@dataclass(frozen=True)
class StoredCalibration:
    """What a session holds: ``complete`` (reusable as it is) or ``why`` not; ``stages`` the
    closing record's rows and ``results`` the stored results it lists, by kind (both empty
    without a complete record)."""

    complete: bool
    why: str = ""
    stages: tuple[StageRun, ...] = ()
    results: dict[str, ResultRecord] = field(default_factory=dict)


def frames_digest(store: Store, session_id: int) -> str:
    """SHA-256 over the session's frame rows (id and content hash, in id order): changes when a
    frame is added, replaced or removed."""
    h = hashlib.sha256()
    for f in store.frames(session_id):
        h.update(f"{f.id}:{f.sha256}\n".encode())
    return h.hexdigest()


def record_run(store: Store, session_id: int, run: CalibrationRun) -> int:
    """Store the record closing a run of every stage (``run.frames_digest``: :func:`frames_digest`
    of the frames the run read); returns its result id."""
    return store.add_calibration(session_id, RUN_KIND, result=run.to_json())


def stored_calibration(store: Store, session_id: int) -> StoredCalibration:
    """The session's calibration as stored: complete, or why not (none, a run cut short, frames
    captured or replaced since)."""
    # the stages' kinds, not the runner's metering (stored with the capture) or an import's
    results = [r for r in store.results(session_id, "calibration") if r.kind in RECORDS]
    if not results:
        return StoredCalibration(False, "no calibration is stored")
    last = results[-1]
    if last.kind != RUN_KIND:
        stages = sorted({r.kind for r in results if r.kind != RUN_KIND})
        return StoredCalibration(False, f"the stored calibration is incomplete (a run stopped after storing "
                                        f"{', '.join(stages)}): it is run again")
    run: CalibrationRun = read_record(last)
    if run.frames_digest != frames_digest(store, session_id):
        return StoredCalibration(False, "frames were captured or replaced since the session was calibrated: "
                                        "the calibration is run again")
    by_id = {r.id: r for r in results}
    listed = {by_id[s.calibration_id].kind: by_id[s.calibration_id] for s in run.stages
              if s.calibration_id in by_id}
    return StoredCalibration(True, "", run.stages, listed)
