"""Distant-source shading against closed forms (Lambertian sphere, uniform sky, one lamp)."""
import numpy as np
import pytest

from reconstruct.brdf import Lambertian, Ward
from reconstruct.distant import shade_distant, sphere_normals
from reconstruct.envmap import EnvironmentMap


def test_sphere_normals_geometry():
    normals, mask = sphere_normals((60, 80))
    assert normals.shape == (60, 80, 3) and mask.shape == (60, 80)
    n = normals[mask]
    assert np.allclose(np.linalg.norm(n, axis=1), 1.0)
    assert np.all(n[:, 2] <= 0)                      # facing the camera looking along +z
    # the disc of radius 30 px covers pi r^2 pixels (to the pixelisation of its outline)
    assert abs(mask.sum() - np.pi * 30 ** 2) < 2 * np.pi * 30
    assert not mask[:, :10].any() and not mask[:, -10:].any()
    assert np.all(normals[~mask] == 0)


def test_lambertian_under_directional_light_matches_cosine_law():
    normals, mask = sphere_normals(41)
    n = normals[mask]
    light = np.array([0.3, -0.4, -np.sqrt(1 - 0.25)])
    albedo = np.array([0.2, 0.5, 0.8])
    L = shade_distant(Lambertian(albedo), n, light[None], np.array([[2.0, 2.0, 2.0]]))
    expected = albedo / np.pi * 2.0 * np.clip(n @ light, 0, None)[:, None]
    assert np.allclose(L, expected, rtol=1e-12, atol=1e-15)


def test_lambertian_under_uniform_sky_reflects_albedo_times_radiance():
    # a uniform environment of radiance L gives irradiance pi L on any plane: L_o = albedo * L
    env = EnvironmentMap.constant([1.0, 2.0, 3.0], height=96)
    normals, mask = sphere_normals(31)
    L = shade_distant(Lambertian(0.6), normals[mask], *env.sources())
    assert np.allclose(L, 0.6 * np.array([1.0, 2.0, 3.0]), rtol=5e-3)


def test_per_point_parameters_and_view_dependence():
    normals, mask = sphere_normals(23)
    n = normals[mask]
    albedo = np.linspace(0.1, 0.9, len(n))
    light = np.array([[0.0, 0.0, -1.0]])
    L = shade_distant(Lambertian(albedo), n, light, np.ones(1))
    assert np.allclose(L[:, 0], albedo / np.pi * -n[:, 2])
    # a glossy lobe: the brightest point is where the normal bisects light and view
    view = np.array([0.6, 0.0, -0.8])
    L = shade_distant(Ward(rho_d=0.0, rho_s=0.3, alpha=0.1), n, light,
                      np.ones(1), view_dirs=view)
    h = (light[0] + view) / np.linalg.norm(light[0] + view)
    assert np.degrees(np.arccos(n[np.argmax(L[:, 0])] @ h)) < 6.0


def test_environment_matches_irradiance_integral():
    rng = np.random.default_rng(3)
    env = EnvironmentMap(rng.random((16, 32, 3)) * 4)
    n = rng.normal(size=(50, 3))
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    L = shade_distant(Lambertian(1.0), n, *env.sources(), view_dirs=n)
    assert np.allclose(L, env.irradiance(n) / np.pi, rtol=1e-9)


@pytest.mark.parametrize("kwargs, match", [
    (dict(normals=np.ones((4, 3))), "normals must be unit"),
    (dict(normals=np.zeros((4, 2))), "normals must have shape"),
    (dict(radiance=-np.ones(1)), "radiance must be finite"),
    (dict(solid_angle=np.ones(2)), "solid_angle must be"),
    (dict(view_dirs=(0, 0, 2.0)), "view_dirs must be unit"),
])
def test_bad_input_names_the_argument(kwargs, match):
    args = dict(normals=np.tile([0.0, 0.0, -1.0], (4, 1)), directions=np.array([[0, 0, -1.0]]),
                radiance=np.ones(1))
    args.update(kwargs)
    with pytest.raises(ValueError, match=match):
        shade_distant(Lambertian(0.5), **args)
