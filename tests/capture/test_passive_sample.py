"""Passive reflectometry on the demo lab's sample sphere (issue 24), for a material the demo does not
use: the ``passive_sphere`` scene rendered by the simulated lab (Grace Cathedral, lamp off, the
renderer's Monte-Carlo environment sampling), the pipeline's sphere geometry from the lab's stated
radius and centre (:func:`capture.pipeline.process.sphere_passive_input`), the pipeline's passive
adapter and its scoring against the truth (:mod:`capture.pipeline.passive_sample`). The camera and
the room's light are the simulation's own here (the demo's session, in tests/capture/test_demo.py,
goes through the calibrated camera and the mirror-probe map)."""
from __future__ import annotations

import numpy as np
import pytest

from capture.pipeline.demo_lab import DemoLab, DemoTruth
from capture.pipeline.images import StepImage
from capture.pipeline.methods import fit_method
from capture.pipeline.passive_sample import score_sample_sphere
from capture.pipeline.process import (ProcessInputs, SessionCalibration, sample_sphere_of,
                                      sphere_passive_input)
from capture.plan import Step
from reconstruct.brdf import CookTorrance
from reconstruct.lumitexels import Lumitexels
from sims.targets import SAMPLE_MATERIAL, SampleSphere
from sims.world import SimWorld, sample_sphere_target


def _empty_lumitexels() -> Lumitexels:
    """The adapter's training lumitexels (passive fits the image alone; they only fill the call)."""
    z3 = np.zeros((0, 3))
    return Lumitexels(position=np.zeros((1, 3)), normal=np.array([[0.0, 0, 1]]), best_view=np.zeros(1, int),
                      pixel=np.zeros((1, 2)), texel=np.zeros(0, int), view=np.zeros(0, int), wi=z3, wo=z3,
                      reflectance=z3, weight=np.zeros(0))


@pytest.mark.parametrize("material, vs_matte", [
    # measured Eq. 1 error 0.371, the best matte BRDF's 0.686; under Uffizi 0.068 off the truth
    (SAMPLE_MATERIAL, 0.65),                                           # the demo's: GGX alpha 0.12
    # measured 0.402 against the matte 0.522 (a rougher lobe is nearer matte); Uffizi 0.035
    (CookTorrance(kd=(0.10, 0.25, 0.45), f0=0.04, alpha=0.2), 0.85),   # bluer and rougher
])
def test_a_glossy_sample_sphere_comes_back_closer_than_a_matte_guess(shared_data, material, vs_matte):
    """The recovered BRDF's Romeiro Eq. 1 error (per sample, 45 x 45 x 90 grid) against the true
    material below 0.45 and below ``vs_matte`` x the best matte (Lambertian) BRDF's, and the
    recovered BRDF rendered under another room's light (Uffizi, never seen) within 15 % of the
    truth's render. With the true camera and a 32-row map of the room (the size the renders use)."""
    lab = DemoLab()
    truth = lab.truth()
    world = SimWorld.for_capture("passive_sphere", camera=lab.camera, seed=9)
    world.targets = [sample_sphere_target(SampleSphere(truth.sample_sphere.radius_mm, material))]
    radiance = world.radiance({})
    room = world.environment.resized(32)   # the size of the demo's calibrated probe map
    cal = SessionCalibration(camera=lab.camera, angle_scale=1.0, lights_mm={}, light_source="none",
                             light_intensity=np.ones(3), absolute=False, environment=room,
                             environment_weight=None, ids={})
    step = Step(0, "passive_sphere", "passive_sphere", 0.0, None, 0.0, (0.01,))
    image = StepImage(0, step, radiance, np.ones(radiance.shape[:2], bool), [], [0.01], 0, 0.0, 10.0)
    sphere = sample_sphere_of(lab.targets())
    assert sphere.radius_mm == 30.0 and np.allclose(sphere.centre_mm, (0, 0, 55))   # the lab states it
    p = sphere_passive_input(image, cal, sphere)
    assert 1400 < p.mask.sum() < 2000   # a 30 mm ball 690 mm from a 560 px focal length: ~1600 px
    inputs = ProcessInputs(calibration=cal, views=[], held_out=[], view_steps=[], held_out_steps=[],
                           view_frames=[], passive=p)
    fit = fit_method("passive", _empty_lumitexels(), inputs, rng=0)
    assert not any("multi-material" in w for w in fit.warnings)
    score = score_sample_sphere(fit.brdf(np.zeros(1, int)), fit.arrays["lambertian"], p, truth=material,
                                held_out_environment=DemoTruth.held_out_environment())
    f = score.figures
    assert f["eq1_error"] < 0.45 and f["eq1_error"] < vs_matte * f["eq1_error_lambertian"], f
    assert f["held_out_env_rel_rms"] < 0.15, f
    # the fit explains the photograph as well as the truth does under the same map (seen 0.085
    # and 0.070 against the truth's 0.094 and 0.075: Monte-Carlo render noise)
    assert f["render_rel_rms"] < 1.05 * f["floor_render_rel_rms"] < 0.15, f
    assert score.pictures["sample_truth"].shape == score.pictures["sample_recovered"].shape
