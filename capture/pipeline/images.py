"""A session's images: stored raw frames -> HDR radiance per step, for calibration and processing.

One path for every step: the camera's bytes -> :func:`calibration.raw.read_raw` ->
:func:`calibration.hdr.merge_raw_brackets` in the mosaic domain (each frame less the master dark
of its exposure, else the black level alone; unclipped samples weighted by inverse variance with
the read noise measured on the darks) -> bilinear demosaic. Radiance unit: DN per second, camera
RGB, float32 H x W x 3; pixels x right, y down.

The master darks come from the dark calibration stage: :mod:`capture.pipeline.calibrate` computes
them into :attr:`SessionImages.darks` during a run, :mod:`capture.pipeline.process` loads the
stored ones (:meth:`SessionImages.use_stored_darks`), both keyed by exposure time in seconds.
"""
from __future__ import annotations

import io
from dataclasses import dataclass

import cv2
import numpy as np

from calibration.hdr import merge_raw_brackets
from calibration.raw import RawMosaic, demosaic_bilinear, read_raw

from ..plan import Step
from ..store import FrameRecord, Store

#: a master dark serves frames whose exposure is within this fraction of its own
DARK_EXPOSURE_TOLERANCE = 0.01


class FrameDataError(ValueError):
    """A stored frame cannot become an image (no exposure time); the message names the frame."""


def exposure_s(f: FrameRecord) -> float:
    """A frame's exposure time, s: the camera's read-back, else the requested one."""
    t = f.exposure_s if f.exposure_s else f.exposure_requested_s
    if not t or t <= 0:
        raise FrameDataError(f"frame {f.id} (step {f.step}) has no exposure time")
    return float(t)


def dark_artifact_name(exposure: float) -> str:
    """The stored artifact name of the master dark at ``exposure`` seconds (``.npy``, DN)."""
    return f"dark_{exposure:g}s.npy"


@dataclass
class StepImage:
    """One step's merged HDR image and what the merge found.

    ``radiance`` (H, W, 3) float32 DN/s; ``valid`` (H, W) bool: no photosite of the pixel's 3 x 3
    demosaic neighbourhood clipped in every exposure; ``saturated_fraction`` of photosites clipped
    everywhere; ``dynamic_range_stops`` log2 of the brightest to the 1st-percentile radiance;
    ``dark_subtracted`` frames that had a master dark of their exposure."""

    step: int
    spec: Step
    radiance: np.ndarray
    valid: np.ndarray
    frame_ids: list[int]
    exposures_s: list[float]
    dark_subtracted: int
    saturated_fraction: float
    dynamic_range_stops: float


class SessionImages:
    """The frames of a session's planned steps, by step, and the master darks the merge uses.

    ``darks`` maps exposure (s) -> master dark (DN, black level included, mosaic shape);
    ``read_noise_dn`` is the darks' frame-to-frame scatter (None: unknown, 1 DN is assumed).
    """

    def __init__(self, store: Store, session: str) -> None:
        self.store = store
        self.info = store.session(session)
        self.steps: dict[int, Step] = {s.index: s.step for s in store.steps(self.info.id)}
        self.by_step: dict[int, list[FrameRecord]] = {}
        for f in store.frames(self.info.id):
            if f.step in self.steps:
                self.by_step.setdefault(f.step, []).append(f)
        self.darks: dict[float, np.ndarray] = {}
        self.read_noise_dn: float | None = None

    def use_stored_darks(self, exposures_s: list[float], artifacts: dict[str, str],
                         read_noise_dn: float | None) -> None:
        """Load the master darks a dark calibration stored: one artifact per exposure (s)."""
        self.read_noise_dn = read_noise_dn
        for t in exposures_s:
            sha = artifacts[dark_artifact_name(t)]
            self.darks[float(t)] = np.load(io.BytesIO(self.store.read_object(sha)))

    def raw(self, f: FrameRecord) -> RawMosaic:
        return read_raw(self.store.read_object(f.sha256), name=f"frame {f.id} (step {f.step})")

    def dark(self, exposure: float) -> np.ndarray | None:
        """The master dark within :data:`DARK_EXPOSURE_TOLERANCE` of ``exposure`` s, or None."""
        for t, dark in self.darks.items():
            if abs(t - exposure) <= DARK_EXPOSURE_TOLERANCE * exposure:
                return dark
        return None

    def merge(self, step: int) -> StepImage:
        """HDR radiance of one step's frames (all brackets and repeats), dark-subtracted.

        Raises
        ------
        FrameDataError
            The step has no stored frames, or a frame has no exposure time (names it).
        calibration.errors.CalibrationError
            A frame's bytes are not a raw the reader understands (names the frame).
        """
        frames = self.by_step.get(step)
        if not frames:
            raise FrameDataError(f"step {step} has no stored frames")
        ts = [exposure_s(f) for f in frames]
        raws = [self.raw(f) for f in frames]
        found = [self.dark(t) for t in ts]
        # a frame without a dark at its exposure falls back to the black level alone
        darks = np.stack([raws[0].black_level if d is None else d for d in found])
        hdr = merge_raw_brackets([r.data for r in raws], ts, black_level=raws[0].black_level,
                                 white_level=raws[0].white_level,
                                 read_noise_dn=self.read_noise_dn or 1.0, darks=darks)
        img = demosaic_bilinear(hdr.radiance, raws[0].channels)
        clipped = cv2.dilate(hdr.saturated.astype(np.uint8), np.ones((3, 3), np.uint8)) > 0
        pos = hdr.radiance[~hdr.saturated & (hdr.radiance > 0)]
        dr = float(np.log2(pos.max() / max(np.percentile(pos, 1), 1e-12))) if pos.size else 0.0
        return StepImage(step=step, spec=self.steps[step], radiance=img, valid=~clipped,
                         frame_ids=[f.id for f in frames], exposures_s=sorted(set(ts)),
                         dark_subtracted=sum(d is not None for d in found),
                         saturated_fraction=float(hdr.saturated.mean()),
                         dynamic_range_stops=round(dr, 2))
