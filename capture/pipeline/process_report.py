"""What ``gonio process`` did, as the report and the console read it: :class:`ProcessReport`,
each method's :class:`MethodOutcome` and the held-out :class:`Floor`
(:func:`capture.pipeline.run.process_session` and
:func:`capture.pipeline.imported.process_imported_session` fill them)."""
from __future__ import annotations

from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

__all__ = ["Floor", "MethodOutcome", "ProcessReport"]


@dataclass(frozen=True)
class Floor:
    """The floor of the held-out scores: the simulation's true model (true ``f_r cos`` about the
    true normals) scored exactly as each method is, by :func:`reconstruct.metrics.relative_rms`
    (and its trimmed variant) of its prediction against the held-out captures. What is left is
    the captures' own error (sensor noise, calibration, resampling onto the mesh): no model of
    these captures can be expected to score lower. Unitless."""

    held_out_rel_rms: float
    held_out_rel_rms_trimmed: float

@dataclass
class MethodOutcome:
    """One method's run: ``status`` ``ok`` (fitted and stored now), ``done`` (stored before),
    ``skipped`` (reason) or ``failed`` (error)."""

    method: str
    status: str
    reason: str = ""
    figures: dict[str, Any] = field(default_factory=dict)
    result_id: int | None = None
    seconds: float = 0.0
    warnings: list[str] = field(default_factory=list)
    #: held-out rel. RMS / the floor's (and the trimmed pair); None without a floor
    floor_ratio: float | None = None
    floor_ratio_trimmed: float | None = None
    #: why the captured object breaks the method's assumption (empty: it does not, or unknown)
    outside_assumption: str = ""


@dataclass
class ProcessReport:
    """What :func:`capture.pipeline.run.process_session` did: calibration stages (stage, status, reason, figures),
    the inputs' counts, each method's outcome, stage timings (s) and, with truth, the
    calibration's errors against it."""

    session: str
    calibration: list[dict[str, Any]] = field(default_factory=list)
    inputs: dict[str, Any] = field(default_factory=dict)
    methods: list[MethodOutcome] = field(default_factory=list)
    timings: dict[str, float] = field(default_factory=dict)
    calibration_truth: dict[str, Any] = field(default_factory=dict)
    floor: Floor | None = None
    report_path: Path | None = None

    def summary(self) -> dict[str, Any]:
        """Everything but the pictures, JSON-able (written beside the HTML as ``.json``)."""
        return {"session": self.session, "calibration": self.calibration, "inputs": self.inputs,
                "calibration_truth": self.calibration_truth, "timings": self.timings,
                "floor": None if self.floor is None else asdict(self.floor),
                "methods": [asdict(m) for m in self.methods], "report": str(self.report_path)}

    def method(self, name: str) -> MethodOutcome:
        for m in self.methods:
            if m.method == name:
                return m
        raise KeyError(f"no method {name!r} in this run")
