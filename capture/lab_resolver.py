"""The one place a session's lab is resolved: what the user gave, completed by the built-in
simulated lab for a session recorded in it.

:func:`resolve_lab` is called once per command (``gonio calibrate`` / ``process``, the console,
``gonio demo``, ``gonio export``) and its :class:`capture.lab.SessionLab` is passed down; the
calibration and processing do not look at the rig snapshots themselves.
"""
from __future__ import annotations

from typing import Any, Mapping

from .lab import GrayCardPose, LabTargets, SessionLab
from .pipeline.demo_lab import demo_lab_for
from .pipeline.process import ProcessError
from .rigs import recorded_in_built_in_lab
from .store import Store

__all__ = ["resolve_lab"]


def resolve_lab(store: Store, session: str, *, mesh: Any = None, targets: LabTargets | None = None,
                gray_card: GrayCardPose | None = None, probe_reflectance: float | None = None, truth: Any = None,
                method_options: Mapping[str, Mapping[str, Any]] | None = None) -> SessionLab:
    """The session's lab: the given parts, and for a session recorded in the built-in simulated
    lab (:func:`capture.rigs.recorded_in_built_in_lab`: every rig snapshot says so) the lab's own
    for each part not given (:meth:`capture.pipeline.demo_lab.DemoLab.session_lab`, at the
    resolution of the session's frames); ``method_options`` given replace the lab's per method.

    Raises
    ------
    capture.store.SessionNotFound
        No such session.
    capture.pipeline.process.ProcessError
        A session of the simulated lab without frames yet (its camera is not known).
    ValueError
        ``probe_reflectance`` outside (0, 1].
    """
    snapshots = store.rig_snapshots(store.session(session).id)
    given = dict(targets=targets, mesh=mesh, gray_card=gray_card, probe_reflectance=probe_reflectance, truth=truth)
    if not recorded_in_built_in_lab(snapshots):
        rigs = {str(t.get("name", "a rig file")) if isinstance(t := s["config"].get("rig", {}), dict) else repr(t)
                for s in snapshots}
        return SessionLab(session, False, targets, mesh, gray_card,
                          1.0 if probe_reflectance is None else probe_reflectance, truth,
                          dict(method_options or {}), tuple(sorted(rigs)))
    if not store.progress(store.session(session).id).frames_stored:   # a capture stopped before its first frame
        raise ProcessError(f"session {session!r} has no frames yet; capture them first: gonio capture "
                           f"resume {session}")
    own = demo_lab_for(store, session).session_lab(session)
    parts = {k: getattr(own, k) if v is None else v for k, v in given.items()}
    return SessionLab(session, True, method_options={**own.method_options, **(method_options or {})},
                      recorded_on=own.recorded_on, **parts)
