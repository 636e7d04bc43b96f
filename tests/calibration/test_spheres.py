"""calibration.spheres: images of mirror spheres -> light directions, and the session pieces
(projected discs, lamp spots and their choice) against closed forms and rendered truth."""
from __future__ import annotations

import numpy as np
import pytest

from calibration.errors import InvalidInput, TooFewViews
from calibration.lights import SphereImage, detect_sphere
from calibration.spheres import (LampSpot, lamp_spots, light_directions_from_sphere, pick_lamp_highlights,
                                 project_spheres)
from test_lights import _angle_deg, _unit, render_spheres

K = np.array([[1200.0, 0, 319.5], [0, 1200.0, 239.5], [0, 0, 1]])
SIZE = (640, 480)
LIGHTS = np.array([[0.3, -0.4, -0.8], [-0.1, 0.2, -1.0], [0.6, 0.5, -0.5], [-0.5, -0.3, -0.7]])


@pytest.mark.parametrize("centre", [[0.0, 0.0, 600.0], [40.0, -30.0, 560.0]])
def test_light_directions_from_images_both_models(centre):
    C, R = np.array(centre), 40.0
    imgs = [render_spheres(C, R, light_dir=L, K=K, size=SIZE)[0] for L in LIGHTS]
    mask = render_spheres(C, R, light_dir=LIGHTS[0], K=K, size=SIZE)[1]
    persp = light_directions_from_sphere(imgs, mask, K=K, radius_mm=R, saturation=1.0)
    assert persp.model == "perspective" and persp.directions.shape == (4, 3)
    # an ~80 px ball: the centre from its pixel outline limits it (seen: 0.04-0.32 deg)
    assert _angle_deg(persp.directions, LIGHTS).max() < 0.5
    assert np.linalg.norm(persp.center_mm - C) < 0.005 * C[2]
    # the reflection points lie on the sphere
    np.testing.assert_allclose(np.linalg.norm(persp.points_mm - persp.center_mm, axis=1), R, rtol=0.01)
    # orthographic: off by about the angle the sphere's rays spread over (its half-angle + off-axis)
    ortho = light_directions_from_sphere(imgs, mask)
    spread = np.degrees(np.arcsin(R / np.linalg.norm(C))) + np.degrees(np.arctan(np.linalg.norm(C[:2]) / C[2]))
    assert ortho.model == "orthographic" and _angle_deg(ortho.directions, LIGHTS).max() < 2 * spread
    # geometry known beforehand: a SphereImage without placeholder fields
    known = SphereImage(ortho.sphere.center_px, ortho.sphere.radius_px)
    np.testing.assert_allclose(light_directions_from_sphere(imgs, known).directions, ortho.directions)


def test_light_directions_arguments_are_checked():
    with pytest.raises(TooFewViews):
        light_directions_from_sphere([])
    with pytest.raises(InvalidInput, match="both K and radius_mm"):
        light_directions_from_sphere([np.zeros((20, 20))], K=K)
    with pytest.raises(InvalidInput, match="names"):
        light_directions_from_sphere([np.zeros((20, 20))], names=["a", "b"])


def test_projected_discs_closed_form():
    centres = np.array([[0.0, 0.0, 500.0], [100.0, 50.0, 800.0], [2000.0, 0.0, 500.0]])
    spheres, inside = project_spheres(centres, 10.0, K, None, SIZE)
    assert inside.tolist() == [0, 1]  # the third projects far right of the image
    np.testing.assert_allclose(spheres[0].center_px, [319.5, 239.5], atol=1e-9)
    np.testing.assert_allclose(spheres[1].center_px, [319.5 + 1200 * 100 / 800, 239.5 + 1200 * 50 / 800])
    for sp, C in zip(spheres, centres):
        assert sp.radius_px == pytest.approx(1200 * np.tan(np.arcsin(10 / np.linalg.norm(C))), rel=1e-9)
    with pytest.raises(InvalidInput, match="behind"):
        project_spheres([[0, 0, -100.0], [0, 0, 500.0]], 10.0, K, None, SIZE)


def _true_highlights(centres, radius, light):
    """Exact highlight pixels of a point light on spheres (the normal bisecting the directions
    to the light and to the camera, by fixed-point iteration)."""
    n = _unit(_unit(light - centres) + _unit(-centres))
    for _ in range(100):
        X = centres + radius * n
        n = _unit(_unit(light - X) + _unit(-X))
    X = centres + radius * n
    return (X @ K.T)[:, :2] / X[:, 2:]


@pytest.mark.parametrize("seed", [0, 1])
def test_the_spot_combination_whose_rays_meet_is_picked(seed):
    rng = np.random.default_rng(seed)
    R = 12.7
    centres = np.array([[-80.0 + 40 * i, 20.0, 600.0 + 5 * i] for i in range(4)])
    light = np.array([rng.uniform(-300, 300), -400.0, rng.uniform(100, 300)])
    truth = _true_highlights(centres, R, light)
    spots = []
    for k, xy in enumerate(truth):  # each ball: the lamp and a brighter decoy a few px away
        decoy = LampSpot(xy + rng.uniform(3, 6, 2) * rng.choice([-1, 1], 2), flux=10.0)
        spots.append([decoy, LampSpot(xy, flux=5.0)] if k % 2 == 0 else [LampSpot(xy, flux=5.0), decoy])
    hl, kept = pick_lamp_highlights(spots, centres, R, K)
    assert kept.tolist() == [0, 1, 2, 3]
    np.testing.assert_allclose(hl, truth, atol=1e-9)
    with pytest.raises(TooFewViews):
        pick_lamp_highlights([spots[0], []], centres[:2], R, K)


def test_lamp_spots_on_a_rendered_ball():
    C, R, light = np.array([10.0, -5.0, 500.0]), 30.0, np.array([200.0, -300.0, 100.0])
    img, mask = render_spheres(C, R, light_pos=light, K=K, size=SIZE, lobe_deg=1.0)
    spots = lamp_spots(img, detect_sphere(mask), 0.5)
    assert len(spots) == 1
    assert np.linalg.norm(spots[0].xy_px - _true_highlights(C[None], R, light)[0]) < 0.5
