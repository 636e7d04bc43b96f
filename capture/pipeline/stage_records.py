"""Each calibration stage's stored result as one typed record, with its JSON codec.

:func:`capture.pipeline.calibrate.calibrate_session` builds a record per stage and stores
``record.to_json()`` (``Store.add_calibration(kind=record.KIND)``); every reader
(:func:`capture.pipeline.process.read_calibration`, :mod:`capture.pipeline.calibration_record`)
gets it back with :func:`read_record`. The codec is derived from each record's field types:
arrays (``np.ndarray``) are stored as nested lists and come back as float arrays, nested rows as
objects, tuples as lists.

Formats: ``"format": 2`` is written. Results stored before the records existed (no ``format``
key, format 1) hold the same data plus a few prose keys describing it (``unit``, ``meaning``,
``artifacts``, the lights' and turntable's ``frames`` / ``frame`` notes); they are read as they
are, their prose ignored (the docstrings below say it). A key missing from a result is read as
the field's default where it has one (keys added over time), else
:class:`RecordFormatError`.

Frames and units: the lab frame of :mod:`capture.pipeline.calibrate` (origin on the turntable
axis at the platter, +z up, +x towards the camera) and the camera frame (OpenCV), mm; pixels;
degrees; seconds; radiance DN/s of camera RGB.
"""
from __future__ import annotations

import types
import typing
from dataclasses import MISSING, dataclass, fields, is_dataclass
from typing import Any, ClassVar, Union

import numpy as np

from calibration.intrinsics import RejectedView
from rig import LightTarget

from ..store import ResultRecord

__all__ = ["FORMAT", "RecordFormatError", "StageRecord", "DarkExposure", "DarkRecord", "HdrStep", "HdrRecord",
           "IntrinsicsRecord", "Pose", "TurntableRecord", "LocatedLight", "UnseenLight", "LightsRecord",
           "StepLight", "PositionerRecord", "PolarizationPose", "PolarizationRecord", "CardReading",
           "GrayCardRecord", "ProbeView", "EnvironmentRecord", "StageRun", "CalibrationRun", "RECORDS",
           "RESULT_KIND", "read_record"]

#: the format :meth:`StageRecord.to_json` writes
FORMAT = 2


class RecordFormatError(ValueError):
    """A stored calibration result cannot be read as its record (the message names the kind,
    the result and the key)."""


# -- the codec ----------------------------------------------------------------------------------
def _encode(value: Any) -> Any:
    if is_dataclass(value):
        return {f.name: _encode(getattr(value, f.name)) for f in fields(value)}
    if isinstance(value, (np.ndarray, np.generic)):
        return value.tolist()
    if isinstance(value, (tuple, list)):
        return [_encode(v) for v in value]
    if isinstance(value, dict):
        return {str(k): _encode(v) for k, v in value.items()}
    return value


def _decode(tp: Any, value: Any, where: str) -> Any:
    origin, args = typing.get_origin(tp), typing.get_args(tp)
    if origin in (Union, types.UnionType):
        if value is None and type(None) in args:
            return None
        (tp,) = [a for a in args if a is not type(None)]
        return _decode(tp, value, where)
    if tp is Any or origin is dict:
        return value
    if value is None:
        raise RecordFormatError(f"{where} is null")
    try:
        if tp is np.ndarray:
            return np.asarray(value, dtype=float)
        if tp in (float, int, str, bool):
            return tp(value)
        if origin is tuple:
            return tuple(_decode(args[0], v, f"{where}[{i}]") for i, v in enumerate(value))
    except (TypeError, ValueError) as exc:
        raise RecordFormatError(f"{where}: {exc}") from None
    if is_dataclass(tp):
        return _from_fields(tp, value, where)
    raise TypeError(f"{where}: no codec for {tp!r}")   # a record field of an unsupported type: a bug


def _from_fields(cls: type, data: Any, where: str, ignore: frozenset[str] = frozenset()) -> Any:
    if not isinstance(data, dict):
        raise RecordFormatError(f"{where} must be an object, got {type(data).__name__}")
    hints = typing.get_type_hints(cls)
    names = {f.name for f in fields(cls)}
    unknown = set(data) - names - ignore
    if unknown:
        raise RecordFormatError(f"{where} has unknown key(s) {', '.join(sorted(unknown))}")
    values = {}
    for f in fields(cls):
        if f.name in data:
            values[f.name] = _decode(hints[f.name], data[f.name], f"{where}.{f.name}")
        elif f.default is MISSING and f.default_factory is MISSING:
            raise RecordFormatError(f"{where} lacks {f.name!r}")
    return cls(**values)


class StageRecord:
    """What every record shares: ``KIND`` (its ``Store.results`` kind), ``STAGE`` (the stage of
    :data:`capture.pipeline.calibrate.STAGES` that stores it), ``PROSE`` (the descriptive keys
    of format 1, ignored) and the codec."""

    KIND: ClassVar[str]
    STAGE: ClassVar[str]
    PROSE: ClassVar[frozenset[str]] = frozenset()

    def to_json(self) -> dict[str, Any]:
        """The record as JSON-able plain values, with ``format``."""
        return {**_encode(self), "format": FORMAT}

    @classmethod
    def from_json(cls, data: dict[str, Any], where: str | None = None):
        """The record of a stored result (format 1 or 2); :class:`RecordFormatError` naming
        ``where`` (default: the kind) and the key."""
        where = where or f"the stored {cls.KIND} calibration"
        if not isinstance(data, dict):
            raise RecordFormatError(f"{where} must be an object, got {type(data).__name__}")
        version = data.get("format", 1)
        if version not in (1, FORMAT):
            raise RecordFormatError(f"{where} has format {version!r}; this gonio reads formats 1 and {FORMAT}")
        body = {k: v for k, v in data.items() if k != "format"}
        return _from_fields(cls, body, where, cls.PROSE if version == 1 else frozenset())


# -- the records, in stage order ----------------------------------------------------------------
@dataclass(frozen=True)
class DarkExposure:
    """The master dark of one exposure (stored as the artifact ``dark_{exposure_s:g}s.npy``,
    DN with the black level): frames averaged, mean and spread above black, hot pixels."""

    exposure_s: float
    frames: int
    mean_above_black_dn: float
    std_dn: float
    hot_pixels: int


@dataclass(frozen=True)
class DarkRecord(StageRecord):
    """``dark``: master darks per exposure; the read noise (DN) from their temporal scatter
    (None: one frame per exposure)."""

    KIND: ClassVar[str] = "dark"
    STAGE: ClassVar[str] = "dark"
    PROSE: ClassVar[frozenset[str]] = frozenset({"artifacts"})
    darks: tuple[DarkExposure, ...]
    read_noise_dn: float | None = None


@dataclass(frozen=True)
class HdrStep:
    """One merged step (:class:`capture.pipeline.images.StepImage`'s figures)."""

    step: int
    kind: str
    frames: int
    exposures_s: tuple[float, ...]
    dark_subtracted: int
    saturated_fraction: float
    dynamic_range_stops: float


@dataclass(frozen=True)
class HdrRecord(StageRecord):
    """``hdr``: the steps merged to radiance (DN/s, camera RGB, bilinear demosaic) and the
    errors of those that could not be."""

    KIND: ClassVar[str] = "hdr"
    STAGE: ClassVar[str] = "hdr"
    PROSE: ClassVar[frozenset[str]] = frozenset({"unit"})
    steps: tuple[HdrStep, ...]
    read_noise_dn: float = 1.0
    errors: tuple[str, ...] = ()


@dataclass(frozen=True)
class IntrinsicsRecord(StageRecord):
    """``intrinsics``: ``K`` (3, 3) and ``dist`` (OpenCV order) for ``image_size`` (width,
    height) px, their standard deviations, the views used (``views``: frame names) and left out,
    the corner coverage grid and the model fitted (``full`` or why constrained)."""

    KIND: ClassVar[str] = "intrinsics"
    STAGE: ClassVar[str] = "intrinsics"
    K: np.ndarray
    dist: np.ndarray
    image_size: tuple[int, ...]
    rms_px: float
    K_std: np.ndarray | None = None
    dist_std: np.ndarray | None = None
    per_view_rms_px: np.ndarray | None = None
    views: tuple[str, ...] = ()
    views_by_kind: dict[str, int] | None = None
    rejected: tuple[RejectedView, ...] = ()
    not_found: tuple[str, ...] = ()
    target: str = ""
    coverage: np.ndarray | None = None
    coverage_fraction: float | None = None
    model: str = "full"
    flags: int = 0
    distortion_note: str = ""


@dataclass(frozen=True)
class Pose:
    """A rigid transform ``X_to = R @ X_from + t_mm``."""

    R: np.ndarray
    t_mm: np.ndarray


@dataclass(frozen=True)
class TurntableRecord(StageRecord):
    """``turntable``: the fit (axis and origin in the camera frame, ``R_ref`` / ``origin_camera_mm``
    in the fit's frame: origin on the axis at the board origin's height, +x along the board's
    first view), its angle model (platter angle = ``angle_scale * reading + angle_offset_deg``)
    and ``lab_to_camera``, the lab frame's pose (origin on the axis at the platter, +x towards the
    camera)."""

    KIND: ClassVar[str] = "turntable"
    STAGE: ClassVar[str] = "turntable"
    PROSE: ClassVar[frozenset[str]] = frozenset({"frames"})
    lab_to_camera: Pose
    angle_scale: float = 1.0
    axis_camera: np.ndarray | None = None
    origin_camera_mm: np.ndarray | None = None
    R_ref: np.ndarray | None = None
    angle_offset_deg: float = 0.0
    fit_status: int = 1
    fit_message: str = ""
    readings_deg: np.ndarray | None = None
    view_angles_deg: np.ndarray | None = None
    per_view_rms_px: np.ndarray | None = None
    rms_px: float | None = None
    axis_std_deg: float | None = None
    target_in_world: Pose | None = None
    camera_centre_lab_mm: np.ndarray | None = None


@dataclass(frozen=True)
class LocatedLight:
    """A light the spheres located: at ``position_camera_mm`` (and ``position_lab_mm`` with a
    lab frame) from the spheres steps ``steps`` (``step`` the first; ``frame`` its first frame
    id) that commanded it (``commanded``: the step's light), with the triangulation's spread
    and residuals (mm), the highlights (px) and spheres used, and the positioner's read-back."""

    step: int
    position_camera_mm: np.ndarray
    commanded: LightTarget | None = None
    position_lab_mm: np.ndarray | None = None
    steps: tuple[int, ...] = ()
    frame: int | None = None
    std_mm: np.ndarray | None = None
    residuals_mm: np.ndarray | None = None
    highlights_px: np.ndarray | None = None
    spheres_used: tuple[int, ...] = ()
    readback_mm: np.ndarray | None = None


@dataclass(frozen=True)
class UnseenLight:
    """A spheres step whose lamp fewer than two spheres show (not a fault: left out)."""

    step: int
    frame: int
    commanded: LightTarget | None
    spheres_showing_lamp: int


@dataclass(frozen=True)
class LightsRecord(StageRecord):
    """``light_positions``: the located lights (camera frame, and lab frame with one), the
    spheres used (radius; the first spheres step's centres, camera and lab frame, and where they
    came from), the steps that could not see the lamp and the errors."""

    KIND: ClassVar[str] = "light_positions"
    STAGE: ClassVar[str] = "lights"
    PROSE: ClassVar[frozenset[str]] = frozenset({"frame"})
    lights: tuple[LocatedLight, ...]
    sphere_radius_mm: float | None = None
    sphere_centres_camera_mm: np.ndarray | None = None
    sphere_centres_lab_mm: np.ndarray | None = None
    sphere_centres_from: str = ""
    spheres_on_turntable: bool = False
    sphere_radii_px: tuple[float, ...] = ()
    errors: tuple[str, ...] = ()
    unseen: tuple[UnseenLight, ...] = ()


@dataclass(frozen=True)
class StepLight:
    """The positioner model's light for one step (lab and camera frame, mm)."""

    step: int
    position_lab_mm: np.ndarray
    position_camera_mm: np.ndarray | None = None


@dataclass(frozen=True)
class PositionerRecord(StageRecord):
    """``positioner_model``: the arm (centre in the lab frame, radius, azimuth / elevation
    offsets, their standard deviations ``param_std``), its fit to the measured lights, and a
    light for every step that commanded azimuth / elevation (``step_lights``)."""

    KIND: ClassVar[str] = "positioner_model"
    STAGE: ClassVar[str] = "positioner"
    step_lights: tuple[StepLight, ...]
    centre_lab_mm: np.ndarray | None = None
    radius_mm: float | None = None
    azimuth_offset_deg: float = 0.0
    elevation_offset_deg: float = 0.0
    param_std: np.ndarray | None = None
    fit_status: int = 1
    fit_message: str = ""
    residuals_mm: np.ndarray | None = None
    rms_mm: float | None = None
    ray_rms_deg: float | None = None


@dataclass(frozen=True)
class PolarizationPose:
    """One pose separated: its steps at analyser ``angles_deg``, the method, the specular share,
    the mean diffuse / specular (DN/s, RGB), parallel / crossed brightness (NaN: not a 0/90 pair)
    and the sinusoid's relative residual (NaN: a 0/90 pair)."""

    steps: tuple[int, ...]
    angles_deg: np.ndarray
    method: str
    specular_fraction: float
    diffuse_mean: np.ndarray
    specular_mean: np.ndarray
    parallel_over_crossed: float
    relative_fit_residual: float


@dataclass(frozen=True)
class PolarizationRecord(StageRecord):
    """``polarization_check``: a few poses separated into diffuse and specular."""

    KIND: ClassVar[str] = "polarization_check"
    STAGE: ClassVar[str] = "polarization"
    poses: tuple[PolarizationPose, ...]


@dataclass(frozen=True)
class CardReading:
    """The gray card in one step: its median value (DN/s, RGB) over ``pixels``, albedo per DN/s,
    spread; with the positioner model the light's distance (mm) and ``brdf_scale_rgb``
    (f_r = value * scale * d^2 / cos_i, card assumed at the lab origin facing the light)."""

    step: int
    value_rgb: np.ndarray
    pixels: int = 0
    relative_scale_rgb: np.ndarray | None = None
    relative_spread: float | None = None
    light_distance_mm: float | None = None
    brdf_scale_rgb: np.ndarray | None = None


@dataclass(frozen=True)
class GrayCardRecord(StageRecord):
    """``gray_card``: the card's ``albedo``, each reading and the median albedo per HDR unit."""

    KIND: ClassVar[str] = "gray_card"
    STAGE: ClassVar[str] = "gray_card"
    PROSE: ClassVar[frozenset[str]] = frozenset({"meaning"})
    albedo: float
    cards: tuple[CardReading, ...]
    relative_scale_rgb: np.ndarray | None = None


@dataclass(frozen=True)
class ProbeView:
    """One mirror-probe view: the ball's centre and radius, px."""

    step: int
    centre_px: np.ndarray
    radius_px: float


@dataclass(frozen=True)
class EnvironmentRecord(StageRecord):
    """``environment_map``: the probe's lat-long map, stored as the artifact ``environment.npz``
    (``env`` (H, 2H, 3) DN/s, ``weight`` (H, 2H) in [0, 1], 0 in the blind cone behind the
    sphere, ``mask`` weight > 0), in the ``frame`` ``lab`` (or ``camera`` without a turntable
    fit); the views merged, the valid share and the mean colour."""

    KIND: ClassVar[str] = "environment_map"
    STAGE: ClassVar[str] = "mirror_probe"
    PROSE: ClassVar[frozenset[str]] = frozenset({"artifacts"})
    frame: str
    height: int
    views: tuple[ProbeView, ...] = ()
    valid_fraction: float | None = None
    mean_rgb: np.ndarray | None = None


@dataclass(frozen=True)
class StageRun:
    """One stage of a whole run: its status, reason and stored result id (None: nothing stored)."""

    stage: str
    status: str
    reason: str = ""
    calibration_id: int | None = None


@dataclass(frozen=True)
class CalibrationRun(StageRecord):
    """``calibration_run``: closes a run of every stage (:mod:`capture.pipeline.calibration_record`):
    each stage's outcome and the SHA-256 of the frames the run read."""

    KIND: ClassVar[str] = "calibration_run"
    STAGE: ClassVar[str] = ""
    stages: tuple[StageRun, ...]
    frames_digest: str


#: the record of each stored calibration kind
RECORDS: dict[str, type[StageRecord]] = {r.KIND: r for r in (
    DarkRecord, HdrRecord, IntrinsicsRecord, TurntableRecord, LightsRecord, PositionerRecord,
    PolarizationRecord, GrayCardRecord, EnvironmentRecord, CalibrationRun)}
#: what each stage's stored result is called in ``Store.results`` (``kind``)
RESULT_KIND: dict[str, str] = {r.STAGE: r.KIND for r in RECORDS.values() if r.STAGE}


def read_record(result: ResultRecord) -> StageRecord:
    """The typed record of a stored calibration result (:class:`RecordFormatError` naming the
    result when it does not read; ``KeyError`` for a kind no stage stores)."""
    if result.kind not in RECORDS:
        raise KeyError(f"calibration result #{result.id} is of kind {result.kind!r}, which no stage "
                       f"stores; stage kinds: {', '.join(RECORDS)}")
    return RECORDS[result.kind].from_json(result.result, f"calibration result #{result.id} ({result.kind})")
