"""Lumitexel assembly against renders with a known BRDF (reconstruct.render as ground truth)."""
import numpy as np
import pytest
import trimesh

from reconstruct.brdf import BlinnPhong, Lambertian
from reconstruct.camera import CameraModel
from reconstruct.lumitexels import Lumitexels, LumitexelError, View, assemble_lumitexels
from reconstruct.raycast import Mesh
from reconstruct.render import PointLight, Scene, render

def material():
    # a glossy plastic: coloured diffuse base and a white Blinn-Phong lobe
    return BlinnPhong(kd=[0.5, 0.35, 0.2], ks=0.4, exponent=30.0)


def turntable(angle_deg):
    a = np.radians(angle_deg)
    T = np.eye(4)
    T[:3, :3] = [[np.cos(a), -np.sin(a), 0], [np.sin(a), np.cos(a), 0], [0, 0, 1]]
    return T


@pytest.fixture(scope="module")
def sphere_capture():
    mesh = trimesh.creation.icosphere(subdivisions=5, radius=40.0)
    mesh.apply_translation([0, 0, 45.0])
    cam = CameraModel.look_at((400, 0, 120), (0, 0, 45), width=160, height=120, fov_deg=18)
    mat = material()
    views = []
    for k, angle in enumerate([0, 60, 120, 180, 240, 300]):
        T = turntable(angle)
        light = np.array([300 * np.cos(np.radians(30 * k - 40)), 300 * np.sin(np.radians(30 * k - 40)),
                          250.0])
        scene = Scene()
        scene.add(Mesh(mesh, T), mat)
        scene.add_light(PointLight(light, intensity=2.0e5))
        res = render(scene, cam)
        views.append(View(camera=cam, radiance=res.radiance, light_position=light,
                          light_intensity=2.0e5, object_to_world=T))
    return mesh, mat, views


def test_samples_match_ground_truth_brdf(sphere_capture):
    mesh, mat, views = sphere_capture
    lt = assemble_lumitexels(mesh, views)
    assert lt.n_texels > 3000 and lt.n_samples > 1.3 * lt.n_texels
    truth = mat.evaluate(lt.wi, lt.wo) * lt.wi[:, 2:3]
    rel = np.abs(lt.reflectance - truth).sum(1) / truth.sum(1)
    # noise-free renders: what remains is bilinear resampling of the shading (worst in highlights)
    assert np.median(rel) < 0.001
    assert np.percentile(rel, 99) < 0.01


def test_positions_and_normals(sphere_capture):
    mesh, _, views = sphere_capture
    lt = assemble_lumitexels(mesh, views)
    centre = np.array([0, 0, 45.0])
    # normals within 0.5 deg of the true sphere's
    true_n = (lt.position - centre) / np.linalg.norm(lt.position - centre, axis=1, keepdims=True)
    ang = np.degrees(np.arccos(np.clip(np.sum(true_n * lt.normal, 1), -1, 1)))
    assert ang.max() < 0.5
    # each texel reprojects onto its own pixel in its best view (within 0.5 px)
    for k, v in enumerate(views):
        sel = lt.best_view == k
        cam = v.camera.with_pose(v.camera.R @ v.object_to_world[:3, :3],
                                 v.camera.R @ v.object_to_world[:3, 3] + v.camera.t)
        err = np.linalg.norm(cam.project(lt.position[sel]) - lt.pixel[sel], axis=1)
        assert err.max() < 0.5


def render_integrated(scene, cam, s=3):
    """Render with each pixel integrating s x s sub-pixels, as a sensor element does."""
    K = cam.K.copy()
    K[:2, :2] *= s
    K[:2, 2] = s * K[:2, 2] + (s - 1) / 2
    hi = CameraModel(K=K, width=cam.width * s, height=cam.height * s, R=cam.R, t=cam.t)
    rad = render(scene, hi).radiance
    return rad.reshape(cam.height, s, cam.width, s, 3).mean(axis=(1, 3))


def test_rejection_at_depth_discontinuities_and_shadow_boundaries():
    # a sphere standing in front of a wall, lit so that it casts shadows onto the wall; the
    # turntable turns between views so samples fall between pixels, and pixels integrate their
    # area, so edge pixels mix surfaces (depth discontinuities) and lit/shadowed wall
    sphere = trimesh.creation.icosphere(subdivisions=4, radius=30.0)
    sphere.apply_translation([0, 0, 40.0])
    wall = trimesh.creation.box(extents=[10, 300, 300])
    wall.apply_translation([-80, 0, 60])
    mesh = trimesh.util.concatenate([sphere, wall])
    cam = CameraModel.look_at((400, 60, 100), (0, 0, 50), width=160, height=120, fov_deg=30)
    views = []
    for angle, (lx, ly) in zip([0, 7, -9], [(250, 150), (250, -150), (300, 0)]):
        light = np.array([lx, ly, 200.0])
        scene = Scene()
        scene.add(Mesh(mesh, turntable(angle)), Lambertian(0.6))
        scene.add_light(PointLight(light, intensity=1e5))
        views.append(View(camera=cam, radiance=render_integrated(scene, cam), light_position=light,
                          light_intensity=1e5, object_to_world=turntable(angle)))

    def bad_fraction(lt):
        truth = 0.6 / np.pi * lt.wi[:, 2:3]
        err = np.abs(lt.reflectance - truth).max(1) / truth.max(1)
        return np.mean(err > 0.05), len(err)

    kept_without, n0 = bad_fraction(assemble_lumitexels(mesh, views, reject_filter_px=0))
    kept_with, n1 = bad_fraction(assemble_lumitexels(mesh, views, reject_filter_px=5))
    print(f"bad samples (>5% off) kept: {kept_without:.2%} of {n0} without rejection, "
          f"{kept_with:.2%} of {n1} with")
    assert kept_without > 0.005         # the scene does produce mixed pixels
    assert kept_with < 0.2 * kept_without
    assert n1 > 0.7 * n0                # rejection removes thin bands, not the data


def test_chunks_and_save_round_trip(sphere_capture, tmp_path):
    mesh, _, views = sphere_capture
    lt = assemble_lumitexels(mesh, views[:3])
    parts = list(lt.chunks(4))
    assert len(parts) == 4
    assert sum(p.n_texels for p in parts) == lt.n_texels
    assert sum(p.n_samples for p in parts) == lt.n_samples
    assert np.array_equal(np.concatenate([p.reflectance for p in parts]), lt.reflectance)
    for p in parts:
        assert np.all(np.diff(p.texel) >= 0) and p.texel.max() == p.n_texels - 1
    lt.save(tmp_path / "lt.npz")
    back = Lumitexels.load(tmp_path / "lt.npz")
    assert np.array_equal(back.wi, lt.wi) and back.diffuse is None


def test_bad_views_are_named():
    cam = CameraModel.look_at((400, 0, 0), width=32, height=24)
    mesh = trimesh.creation.icosphere(radius=10)
    with pytest.raises(LumitexelError, match=r"views\[0\].radiance"):
        assemble_lumitexels(mesh, [View(cam, np.zeros((10, 10, 3)), np.zeros(3))])
    with pytest.raises(LumitexelError, match="no views"):
        assemble_lumitexels(mesh, [])


def test_noisy_samples_are_within_noise_of_ground_truth(sphere_capture):
    # sensor-like noise on every view: shot noise (variance ∝ signal) plus read noise
    mesh, mat, views = sphere_capture
    rng = np.random.default_rng(7)
    gain, read = 2e-4, 2e-4           # radiance units: variance = gain * L + read^2
    noisy, sigmas = [], []
    for v in views:
        sigma = np.sqrt(gain * np.clip(v.radiance, 0, None) + read ** 2)
        noisy.append(View(v.camera, (v.radiance + rng.normal(0, 1, v.radiance.shape) * sigma)
                          .astype(np.float32), v.light_position, v.light_intensity,
                          v.object_to_world))
        sigmas.append(sigma)
    lt = assemble_lumitexels(mesh, noisy)
    truth = mat.evaluate(lt.wi, lt.wo) * lt.wi[:, 2:3]
    # the sample's sigma: the pixel noise at that point (bilinear weights can only lower it),
    # scaled like the sample (d^2 / I)
    sig = np.empty_like(truth)
    for k, v in enumerate(noisy):
        sel = lt.view == k
        cam = v.camera.with_pose(v.camera.R @ v.object_to_world[:3, :3],
                                 v.camera.R @ v.object_to_world[:3, 3] + v.camera.t)
        px = np.rint(cam.project(lt.position[lt.texel[sel]])).astype(int)
        d2 = np.sum((np.linalg.solve(v.object_to_world[:3, :3], v.light_position
                                     - v.object_to_world[:3, 3]) - lt.position[lt.texel[sel]]) ** 2, 1)
        sig[sel] = sigmas[k][px[:, 1], px[:, 0]] * (d2 / v.light_intensity)[:, None]
    z = (lt.reflectance - truth) / sig
    assert abs(z.mean()) < 0.05                     # unbiased
    assert z.std() < 1.05                           # no error beyond the noise
    assert np.mean(np.abs(z) > 4) < 1e-3


def test_polarization_separated_views_give_per_sample_diffuse_and_specular():
    mesh = trimesh.creation.icosphere(subdivisions=4, radius=40.0)
    mesh.apply_translation([0, 0, 45.0])
    cam = CameraModel.look_at((400, 0, 120), (0, 0, 45), width=120, height=90, fov_deg=18)
    mat = material()
    views = []
    for angle in (0, 90, 200):
        light = np.array([250.0, 100.0, 250.0])
        scene = Scene()
        scene.add(Mesh(mesh, turntable(angle)), mat)
        scene.add_light(PointLight(light, intensity=2e5))
        res = render(scene, cam, components=True)
        views.append(View(cam, res.radiance, light, 2e5, turntable(angle),
                          diffuse=res.diffuse, specular=res.specular))
    lt = assemble_lumitexels(mesh, views)
    assert lt.diffuse is not None and lt.specular is not None
    assert np.allclose(lt.diffuse + lt.specular, lt.reflectance, rtol=1e-4, atol=1e-7)
    expected_diffuse = mat.diffuse_part().evaluate(lt.wi, lt.wo) * lt.wi[:, 2:3]
    rel = np.abs(lt.diffuse - expected_diffuse).max(1) / expected_diffuse.max(1)
    assert np.percentile(rel, 99) < 0.01
