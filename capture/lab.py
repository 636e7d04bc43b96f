"""What a lab is, as the pipeline takes it: the user's statement of its targets, and one session's
resolved lab.

:class:`LabTargets` is what a user states about the lab's calibration targets (``gonio calibrate
--targets FILE``); :class:`GrayCardPose` where the gray card stands; :class:`SessionLab` a
session's whole lab (targets, the object's mesh, the card, the probe, the truth of a simulated
session, the methods' options), made once by :func:`capture.lab_resolver.resolve_lab` (the CLI,
the console and the demo call it) and handed down to calibration and processing. This module
imports nothing of the pipeline.

Frames: the *lab frame* (origin on the turntable axis at the platter surface, +z up the axis, +x
towards the camera), mm.
"""
from __future__ import annotations

from dataclasses import dataclass, field, fields
from typing import Any, Mapping

import numpy as np
import trimesh

__all__ = ["LabTargets", "GrayCardPose", "SessionLab", "TargetsNeeded"]


class TargetsNeeded(ValueError):
    """No targets were given for a session not recorded on the simulated lab: its target sizes
    are the lab's own, which only the user knows (the message names the fields)."""


_BOARD_FIELDS = {"chessboard": ("chessboard_inner", "chessboard_square_mm", "chessboard_centre_height_mm"),
                 "charuco": ("charuco_squares", "charuco_square_mm", "charuco_marker_mm",
                             "charuco_centre_height_mm")}


@dataclass(frozen=True)
class LabTargets:
    """The lab's physical calibration targets (what the pipeline looks for), millimetres.

    A real lab states its own (``gonio calibrate --targets FILE``, a TOML file of these field
    names): the board's square size sets the metric scale of the turntable frame. The built-in
    simulated lab states its own (:meth:`capture.pipeline.demo_lab.DemoLab.targets`). A board is
    given by all of its fields or none; at least one board is needed.
    """

    chessboard_inner: tuple[int, int] | None = None
    chessboard_square_mm: float | None = None
    #: height above the platter of the centre of the board's corner grid, mm (puts the lab
    #: origin on the platter; a 180-degree ambiguous chessboard has the same centre either way)
    chessboard_centre_height_mm: float | None = None
    charuco_squares: tuple[int, int] | None = None
    charuco_square_mm: float | None = None
    charuco_marker_mm: float | None = None
    charuco_centre_height_mm: float | None = None
    charuco_dictionary: str = "DICT_5X5_100"
    #: radius of the light-calibration spheres, mm (None: no lights stage)
    sphere_radius_mm: float | None = None
    #: mirror reflectance of the spheres (chrome ~0.65, bearing steel ~0.55): their limb shows
    #: the backdrop times this, which places the silhouette threshold
    sphere_reflectance: float = 0.55
    #: centres of the light-calibration spheres in the lab frame (module docstring), mm; empty
    #: or None: find them from their silhouettes (needs a lit backdrop behind the spheres)
    sphere_centres_mm: tuple[tuple[float, float, float], ...] | None = None
    #: the sphere fixture stands on the platter: ``sphere_centres_mm`` are at turntable reading
    #: 0 and turn with it (spheres captures at several angles spread the spheres around the
    #: axis, a wider baseline for the lamp's depth); False: fixed in the lab
    spheres_on_turntable: bool = False
    gray_card_albedo: float = 0.18
    #: cv2.CALIB_* flags for the intrinsics fit; with k3 free the fit fixes it at 0 when the
    #: views do not determine it (a turntable-only board sweep covers only the image centre)
    intrinsics_flags: int = 0
    #: the homogeneous sample sphere of a ``passive_sphere`` capture: its radius (calipers) and
    #: its centre on its stand, lab frame, mm (both or neither; None: passive reflectometry runs
    #: on the object's ``passive`` capture, if any)
    sample_sphere_radius_mm: float | None = None
    sample_sphere_centre_mm: tuple[float, float, float] | None = None

    def has_board(self, kind: str) -> bool:
        """Whether the ``'chessboard'`` or ``'charuco'`` board is described."""
        return getattr(self, _BOARD_FIELDS[kind][0]) is not None

    def __post_init__(self) -> None:
        for kind, names in _BOARD_FIELDS.items():
            given = [getattr(self, n) is not None for n in names]
            if any(given) and not all(given):
                raise ValueError(f"LabTargets: the {kind} needs all of {', '.join(names)}; missing "
                                 f"{', '.join(n for n, g in zip(names, given) if not g)}")
        if not any(self.has_board(k) for k in _BOARD_FIELDS):
            raise ValueError("LabTargets: describe at least one board (chessboard_* or charuco_* fields)")
        for name in ("chessboard_square_mm", "charuco_square_mm", "charuco_marker_mm", "sphere_radius_mm"):
            value = getattr(self, name)
            if value is not None and not value > 0:
                raise ValueError(f"LabTargets.{name} must be > 0 mm, got {value!r}")
        if not 0 < self.sphere_reflectance < 1:
            raise ValueError(f"LabTargets.sphere_reflectance must be in (0, 1), "
                             f"got {self.sphere_reflectance!r}")
        if not 0 < self.gray_card_albedo <= 1:
            raise ValueError(f"LabTargets.gray_card_albedo must be in (0, 1], got {self.gray_card_albedo!r}")
        for name in ("chessboard_centre_height_mm", "charuco_centre_height_mm"):
            value = getattr(self, name)
            if value is not None and not np.isfinite(value):
                raise ValueError(f"LabTargets.{name} must be a finite number of mm, got {value!r}")
        centres = self.sphere_centres_mm
        if centres is not None and len(centres):
            if self.sphere_radius_mm is None:
                raise ValueError("LabTargets.sphere_centres_mm needs sphere_radius_mm")
            try:
                arr = np.asarray(centres, dtype=float)
            except (TypeError, ValueError):
                raise ValueError(f"LabTargets.sphere_centres_mm must be a list of [x, y, z] mm, "
                                 f"got {centres!r}") from None
            if arr.ndim != 2 or arr.shape[1] != 3 or len(arr) < 2 or not np.all(np.isfinite(arr)):
                raise ValueError(f"LabTargets.sphere_centres_mm must hold >= 2 finite [x, y, z] (mm), "
                                 f"got shape {arr.shape}")
            gaps = np.linalg.norm(arr[:, None] - arr[None], axis=2)[np.triu_indices(len(arr), 1)]
            if gaps.min() < 2 * self.sphere_radius_mm:
                raise ValueError(f"LabTargets.sphere_centres_mm: two centres are {gaps.min():.1f} mm apart, "
                                 f"less than a sphere's diameter ({2 * self.sphere_radius_mm} mm)")
            centres = tuple(tuple(float(v) for v in row) for row in arr)
        # frozen: normalise TOML lists (and an empty list: no positions) in place
        object.__setattr__(self, "sphere_centres_mm", centres if centres else None)
        self._check_sample_sphere()

    def _check_sample_sphere(self) -> None:
        r, c = self.sample_sphere_radius_mm, self.sample_sphere_centre_mm
        if (r is None) != (c is None):
            raise ValueError("LabTargets: the sample sphere needs both sample_sphere_radius_mm and "
                             "sample_sphere_centre_mm (or neither)")
        if r is None:
            return
        if not (isinstance(r, (int, float)) and np.isfinite(r) and r > 0):
            raise ValueError(f"LabTargets.sample_sphere_radius_mm must be > 0 mm, got {r!r}")
        try:
            arr = np.asarray(c, dtype=float)
        except (TypeError, ValueError):
            arr = np.zeros(0)
        if arr.shape != (3,) or not np.all(np.isfinite(arr)):
            raise ValueError(f"LabTargets.sample_sphere_centre_mm must be a finite [x, y, z] (lab frame, mm), "
                             f"got {c!r}")
        object.__setattr__(self, "sample_sphere_centre_mm", tuple(float(v) for v in arr))


@dataclass(frozen=True)
class GrayCardPose:
    """Where the gray card stands at turntable reading 0, lab frame, mm (it turns with the
    platter): its centre and unit normal (printed side). With it the lamp's intensity follows from
    the card's exact distance and incidence angle; without it the calibration's own assumption
    (card at the lab origin facing the light) is used."""

    centre_mm: tuple[float, float, float]
    normal: tuple[float, float, float]


@dataclass(frozen=True)
class SessionLab:
    """One session's lab, resolved once (:func:`capture.lab_resolver.resolve_lab`).

    Attributes
    ----------
    session : str
        The session it was resolved for.
    built_in : bool
        Recorded in the built-in simulated lab (``--rig sim``), which states its own targets,
        mesh, gray-card pose, probe and truth.
    targets : LabTargets or None
        None: not stated (a calibration then needs them: :meth:`require_targets`).
    mesh : trimesh.Trimesh or None
        The object's mesh, object frame (the lab frame at turntable reading 0), mm.
    gray_card : GrayCardPose or None
        The card's pose, for the lamp's absolute intensity.
    probe_reflectance : float
        The mirror probe's reflectance, divided out of the environment map.
    truth : capture.pipeline.demo_lab.DemoTruth or None
        The simulated lab's ground truth (adds truth columns to the report).
    method_options : mapping of str -> mapping
        Per method, its options (:func:`capture.pipeline.methods.fit_method`).
    recorded_on : tuple of str
        The rig names the session's snapshots give (for messages).
    """

    session: str
    built_in: bool = False
    targets: LabTargets | None = None
    mesh: trimesh.Trimesh | None = None
    gray_card: GrayCardPose | None = None
    probe_reflectance: float = 1.0
    truth: Any = None
    method_options: Mapping[str, Mapping[str, Any]] = field(default_factory=dict)
    recorded_on: tuple[str, ...] = ()

    def __post_init__(self) -> None:
        if not 0 < self.probe_reflectance <= 1:
            raise ValueError(f"probe_reflectance must be in (0, 1], got {self.probe_reflectance!r}")

    def require_targets(self) -> LabTargets:
        """The targets, or :class:`TargetsNeeded` saying which fields to state."""
        if self.targets is not None:
            return self.targets
        names = ", ".join(f.name for f in fields(LabTargets))
        raise TargetsNeeded(
            f"session {self.session!r} was recorded on {', '.join(self.recorded_on) or 'an unrecorded rig'}, "
            f"not in the built-in simulated lab (gonio capture run --rig sim), so its targets' sizes are "
            f"unknown: state them with --targets FILE (gonio calibrate; targets= in Python), a TOML "
            f"file of LabTargets fields: {names}")

    def require_mesh(self) -> trimesh.Trimesh:
        """The mesh, or ``ValueError`` saying how to give it."""
        if self.mesh is None:
            raise ValueError("mesh: the object's mesh is needed (gonio process --mesh FILE)")
        return self.mesh
