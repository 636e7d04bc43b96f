"""Passive reflectometry on the lab's homogeneous sample sphere, scored against what is known of it.

Romeiro et al. 2008 recover one BRDF from one image of a known, curved, homogeneous surface under
a known environment. On the sample sphere of a ``passive_sphere`` capture that BRDF is the
sample material's, so it is scored as the paper scores it rather than on the object's held-out
lights (a different surface):

- always: the recovered BRDF rendered on the sphere's pixels under the calibrated room light
  (:func:`reconstruct.distant.shade_distant`, the probe map with its blind cone weighted out,
  area-averaged to :data:`RENDER_MAP_HEIGHT` rows) against the captured image (``render_rel_rms``,
  :func:`reconstruct.metrics.relative_rms`);
- with the simulation's truth: Romeiro's Eq. 1 error against the true material
  (:func:`reconstruct.passive.bivariate_error`, both readings: per sample ``eq1_error``, pooled
  ``eq1_error_pooled``; docs/zoo.md), beside the best constant (Lambertian) BRDF's and the true
  material's own 32 x 32 bivariate reduction's (``eq1_error_reduction``) (the best any bivariate table can do); the
  recovered and the true BRDF rendered under the same calibrated light (``truth_render_rel_rms``)
  and under a held-out environment the fit never saw (``held_out_env_rel_rms``); and the floor
  of the render figures, the true BRDF rendered under the calibrated light against the
  photograph (``floor_render_rel_rms``: what the probe map, the sensor and the geometry leave;
  a wrong BRDF may fit the photograph better than the truth when the map is wrong).

Frames: lab frame (normals, view directions, environment maps); radiance in the image's units
(DN/s), the BRDFs in 1/sr.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

from reconstruct.brdf import BRDF, Bivariate, Lambertian
from reconstruct.distant import shade_distant
from reconstruct.envmap import EnvironmentMap
from reconstruct.metrics import relative_rms
from reconstruct.passive import bivariate_error

from .process import PassiveInput

__all__ = ["EQ1_GRID", "SAMPLE_FIGURES", "SampleScore", "SampleTruth", "score_sample_sphere"]

#: the (theta_h, theta_d, phi_d) grid of the Eq. 1 errors: half MERL's in each angle (the
#: error changes by < 1 % of itself against the full grid on smooth lobes, at an eighth of the cost)
EQ1_GRID = (45, 45, 90)
#: the figures :func:`score_sample_sphere` adds, in the order the report lists them
SAMPLE_FIGURES = ("image_of", "sphere_pixels", "eq1_error", "eq1_error_lambertian", "eq1_error_reduction",
                  "eq1_error_pooled", "render_rel_rms", "floor_render_rel_rms", "truth_render_rel_rms",
                  "held_out_env_rel_rms")
#: rows of the room's map the renders use (5.6 deg texels, under half the width of the demo
#: sample's GGX lobe): the calibrated probe map's 128 rows cost 12 s of CPU per render of the
#: sphere on the loaded 2-core machine, 64 rows 3 s
RENDER_MAP_HEIGHT = 32
#: pixels of margin around the sphere in the stored pictures
CROP_MARGIN_PX = 4


@dataclass(frozen=True)
class SampleScore:
    """The sample sphere's figures (JSON-able; keys as in the module docstring) and pictures
    (``sample_captured``, ``sample_recovered``, with truth ``sample_truth``, and under the held-out
    environment ``sample_heldout_truth`` / ``sample_heldout_recovered``: (h, w, 3) radiance cropped
    to the sphere, NaN off its used pixels)."""

    figures: dict[str, Any]
    pictures: dict[str, np.ndarray] = field(default_factory=dict)


@dataclass(frozen=True)
class SampleTruth:
    """The sample sphere's truth as :func:`capture.pipeline.pictures.method_pictures` reads a
    truth: one material at every point, no normal detail."""

    material: BRDF

    def materials(self, points: np.ndarray) -> tuple[np.ndarray, tuple[BRDF, ...]]:
        return np.zeros(len(points), int), (self.material,)

    @staticmethod
    def normals(points: np.ndarray) -> None:
        return None


def _room_sources(env: EnvironmentMap, weight: np.ndarray | None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The map's texels as sources, weighted by the trust in each (a probe's blind cone: 0),
    area-averaged to at most :data:`RENDER_MAP_HEIGHT` rows."""
    if weight is not None:
        weight = np.asarray(weight, np.float32).reshape(env.shape)
    if env.shape[0] > RENDER_MAP_HEIGHT:
        if weight is not None:
            w3 = EnvironmentMap(np.repeat(np.clip(weight, 0, 1)[..., None], 3, axis=2)).resized(RENDER_MAP_HEIGHT)
            weight = w3.image[..., 0]
        env = env.resized(RENDER_MAP_HEIGHT)
    d, E, omega = env.sources()
    return (d, E, omega) if weight is None else (d, E * weight.reshape(-1, 1), omega)


def score_sample_sphere(brdf: BRDF, lambertian: np.ndarray, p: PassiveInput, *, truth: BRDF | None = None,
                        held_out_environment: EnvironmentMap | None = None) -> SampleScore:
    """Score the BRDF recovered from the sample sphere's image ``p`` (see the module docstring).

    Parameters
    ----------
    brdf : BRDF
        The recovered BRDF (1/sr).
    lambertian : ndarray (3,)
        The best constant BRDF of the same fit (1/sr).
    p : PassiveInput
        The sample sphere's image, normals, view directions and calibrated environment.
    truth : BRDF, optional
        The sample's true material (simulation only).
    held_out_environment : EnvironmentMap, optional
        Another room's light in the lab frame, for the held-out render (with ``truth``).
    """
    if p.sample_sphere is None:
        raise ValueError("score_sample_sphere: the passive input is not of a sample sphere")
    mask = p.mask
    if not mask.any():
        raise ValueError("score_sample_sphere: the sample sphere has no usable pixels")
    n, v = p.normals[mask], p.view_dirs[mask]
    room = _room_sources(p.environment, p.environment_weight)
    ys, xs = np.nonzero(mask)
    crop = (slice(max(ys.min() - CROP_MARGIN_PX, 0), ys.max() + CROP_MARGIN_PX + 1),
            slice(max(xs.min() - CROP_MARGIN_PX, 0), xs.max() + CROP_MARGIN_PX + 1))

    def picture(values: np.ndarray) -> np.ndarray:
        out = np.full(mask.shape + (3,), np.nan, np.float32)
        out[mask] = values
        return out[crop]

    captured = np.asarray(p.image, float)[mask]
    recovered = shade_distant(brdf, n, *room, view_dirs=v)
    figures: dict[str, Any] = {"image_of": f"the sample sphere (radius {p.sample_sphere.radius_mm:g} mm)",
                               "sphere_pixels": int(mask.sum()),
                               "render_rel_rms": relative_rms(recovered, captured)}
    pictures = {"sample_captured": picture(captured), "sample_recovered": picture(recovered)}
    if truth is None:
        return SampleScore(figures, pictures)
    true_room = shade_distant(truth, n, *room, view_dirs=v)
    figures.update({
        "eq1_error": bivariate_error(brdf, truth, shape=EQ1_GRID),
        "eq1_error_pooled": bivariate_error(brdf, truth, shape=EQ1_GRID, pooled=True),
        "eq1_error_lambertian": bivariate_error(Lambertian(np.asarray(lambertian, float) * np.pi), truth,
                                                shape=EQ1_GRID),
        "eq1_error_reduction": bivariate_error(Bivariate.from_brdf(truth), truth, shape=EQ1_GRID),
        "floor_render_rel_rms": relative_rms(true_room, captured),
        "truth_render_rel_rms": relative_rms(recovered, true_room)})
    pictures["sample_truth"] = picture(true_room)
    if held_out_environment is not None:
        held = held_out_environment.sources()
        want, got = shade_distant(truth, n, *held, view_dirs=v), shade_distant(brdf, n, *held, view_dirs=v)
        figures["held_out_env_rel_rms"] = relative_rms(got, want)
        pictures["sample_heldout_truth"], pictures["sample_heldout_recovered"] = picture(want), picture(got)
    return SampleScore(figures, pictures)
