"""Renderer against closed forms: Lambertian shading, inverse-square falloff, mirror highlights,
cast shadows, polarizers, environment lighting, SVBRDF plumbing and geometry buffers."""
from __future__ import annotations

import re
from dataclasses import replace

import numpy as np
import pytest
import trimesh
from scipy.optimize import least_squares

from reconstruct.brdf import BlinnPhong, CookTorrance, Lambertian
from reconstruct.camera import CameraModel
from reconstruct.envmap import EnvironmentMap
from reconstruct.frames import tangent_frames, to_local
from reconstruct.raycast import Mesh, Plane, Sphere, reflect
from reconstruct.render import (DirectionalLight, MaterialMap, Mirror, PointLight, PrimaryHits,
                                Scene, render, render_rays)


def _unit(v):
    v = np.asarray(v, float)
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


@pytest.fixture
def small_cam():
    """A 64x48 camera 300 mm from a 40 mm sphere at (0, 0, 50) (Monte-Carlo tests)."""
    return CameraModel.look_at((0.0, -300.0, 50.0), (0.0, 0.0, 50.0), width=64, height=48,
                               fov_deg=22)


@pytest.fixture
def sphere_cam():
    """A 120x100 camera 300 mm from a 40 mm sphere at (0, 0, 50)."""
    return CameraModel.look_at((0.0, -300.0, 50.0), (0.0, 0.0, 50.0), width=120, height=100,
                               fov_deg=22)


# ----------------------------------------------------------------------------------------------
# closed forms
# ----------------------------------------------------------------------------------------------
def test_lambertian_sphere_directional_light(sphere_cam):
    albedo = np.array([0.8, 0.5, 0.2])
    E = np.array([2.0, 3.0, 4.0])
    light = _unit([1.0, -2.0, 1.5])
    sc = Scene()
    sc.add(Sphere(40.0, center=(0, 0, 50)), Lambertian(albedo))
    sc.add_light(DirectionalLight(light, irradiance=E))
    res = render(sc, sphere_cam, shadows=True)
    m = res.mask
    assert 0.2 < m.mean() < 0.8
    # buffers: the sphere's own normals and positions
    n = res.normal[m].astype(float)
    p = res.position[m]
    np.testing.assert_allclose(np.linalg.norm(p - [0, 0, 50], axis=1), 40.0, atol=1e-9)
    np.testing.assert_allclose(n, (p - [0, 0, 50]) / 40.0, atol=1e-6)
    expected = albedo / np.pi * E * np.clip(n @ light, 0, None)[:, None]
    np.testing.assert_allclose(res.radiance[m], expected, rtol=1e-5, atol=1e-7)
    assert np.all(res.radiance[~m] == 0)


def test_inverse_square_falloff():
    cam = CameraModel.look_at((0.0, 0.0, 500.0), (0.0, 0.0, 0.0), width=64, height=64, fov_deg=30,
                              up=(0, 1, 0))
    I = 5000.0
    results = []
    for dist in (100.0, 250.0):
        pos = np.array([30.0, -20.0, 0.0]) + dist * _unit([0.2, 0.1, 1.0])
        sc = Scene()
        sc.add(Plane((400, 400)), Lambertian(0.6))
        sc.add_light(PointLight(pos, I))
        res = render(sc, cam)
        p = res.position[res.mask]
        v = pos - p
        r2 = np.einsum("ij,ij->i", v, v)
        cos = v[:, 2] / np.sqrt(r2)
        np.testing.assert_allclose(res.radiance[res.mask][:, 1], 0.6 / np.pi * I * cos / r2,
                                   rtol=1e-5)
        results.append(res)
    # the same pixel: moving the light back along a line through a surface point
    P = np.array([30.0, -20.0, 0.0])
    px = np.round(cam.project(P[None])[0]).astype(int)
    p_hit = results[0].position[px[1], px[0]]
    r1 = np.linalg.norm(P + 100.0 * _unit([0.2, 0.1, 1.0]) - p_hit)
    r2 = np.linalg.norm(P + 250.0 * _unit([0.2, 0.1, 1.0]) - p_hit)
    ratio = results[0].radiance[px[1], px[0], 0] / results[1].radiance[px[1], px[0], 0]
    c1 = (P + 100.0 * _unit([0.2, 0.1, 1.0]) - p_hit)[2] / r1
    c2 = (P + 250.0 * _unit([0.2, 0.1, 1.0]) - p_hit)[2] / r2
    assert ratio == pytest.approx((r2 / r1) ** 2 * c1 / c2, rel=1e-5)
    assert 5.0 < ratio < 7.0  # ~ (250/100)^2 at the pixel on the line


def _mirror_point(center, radius, eye, light):
    """The point of a mirror sphere whose normal bisects the directions to eye and light."""
    def resid(a):
        n = np.array([np.sin(a[0]) * np.cos(a[1]), np.sin(a[0]) * np.sin(a[1]), np.cos(a[0])])
        p = center + radius * n
        h = _unit(_unit(eye - p) + _unit(light - p))
        return np.cross(h, n)
    h0 = _unit(_unit(eye - center) + _unit(light - center))
    a0 = [np.arccos(h0[2]), np.arctan2(h0[1], h0[0])]
    sol = least_squares(resid, a0, xtol=1e-14, ftol=1e-14)
    a = sol.x
    return center + radius * np.array([np.sin(a[0]) * np.cos(a[1]),
                                       np.sin(a[0]) * np.sin(a[1]), np.cos(a[0])])


def test_mirror_sphere_highlight_position():
    center = np.array([0.0, 0.0, 30.0])
    eye = np.array([0.0, -400.0, 80.0])
    light_pos = np.array([250.0, -200.0, 300.0])
    cam = CameraModel.look_at(eye, center, width=400, height=400, fov_deg=10)
    I, r_l = 2.0e5, 20.0
    sc = Scene()
    sc.add(Sphere(25.0, center=center), Mirror(0.9))
    sc.add_light(PointLight(light_pos, I, radius=r_l))
    res = render(sc, cam)
    lit = res.radiance[..., 0] > 0
    assert 3 <= lit.sum() < 200
    # highlight radiance = mirror reflectance x the light sphere's radiance
    np.testing.assert_allclose(res.radiance[lit], 0.9 * I / (np.pi * r_l ** 2), rtol=1e-5)
    ys, xs = np.nonzero(lit)
    expected = cam.project(_mirror_point(center, 25.0, eye, light_pos)[None])[0]
    assert np.hypot(xs.mean() - expected[0], ys.mean() - expected[1]) < 0.5


def test_mirror_reflects_environment_exactly(sphere_cam):
    env = EnvironmentMap.from_function(lambda d: np.stack([1 + d[:, 0], 1 + d[:, 1] ** 2,
                                                           1 + d[:, 2]], axis=1), 32)
    sc = Scene(environment=env)
    sc.add(Sphere(40.0, center=(0, 0, 50)), Mirror((0.5, 0.7, 0.9)))
    res = render(sc, sphere_cam)
    m = res.mask
    o, d = sphere_cam.pixel_rays()
    r = reflect(d[m.ravel()], res.normal[m].astype(float))
    expected = np.array([0.5, 0.7, 0.9]) * env.lookup(r)
    np.testing.assert_allclose(res.radiance[m], expected, rtol=2e-4)
    # background pixels see the environment directly
    np.testing.assert_allclose(res.radiance[~m], env.lookup(d[~m.ravel()]), rtol=1e-6)


@pytest.mark.parametrize("kind", ["directional", "point"])
def test_sphere_shadow_on_plane(kind):
    c, R = np.array([10.0, 5.0, 60.0]), 25.0
    cam = CameraModel.look_at((0.0, -350.0, 350.0), (0.0, 0.0, 0.0), width=160, height=120,
                              fov_deg=50)
    sc = Scene()
    sc.add(Plane((500, 500)), Lambertian(0.5))
    sc.add(Sphere(R, center=c), Lambertian(0.5))
    if kind == "directional":
        l = _unit([0.5, 0.3, 1.0])
        sc.add_light(DirectionalLight(l, 1.0))
    else:
        L = np.array([-120.0, 60.0, 300.0])
        sc.add_light(PointLight(L, 1e5))
    res = render(sc, cam)
    on_plane = res.surface_index == 0
    q = res.position[on_plane]
    dirs = np.broadcast_to(l, q.shape) if kind == "directional" else _unit(L - q)
    # distance from the sphere's centre to the ray q + t dirs (t > 0)
    t = np.einsum("ij,ij->i", c - q, dirs)
    dist = np.linalg.norm(q + t[:, None] * dirs - c, axis=1)
    shadow_expected = (dist < R) & (t > 0)
    shadow = res.radiance[on_plane][:, 0] == 0
    assert shadow_expected.sum() > 200
    clear = np.abs(dist - R) > 0.01 * R  # pixels whose centre is not on the shadow's edge
    np.testing.assert_array_equal(shadow[clear], shadow_expected[clear])


def test_no_shadow_acne_on_mesh_sphere():
    """Shadow rays leave a tessellated sphere cleanly: every face turned to the light is lit."""
    mesh = trimesh.creation.icosphere(subdivisions=4, radius=1.0)
    T = np.diag([30.0, 30.0, 30.0, 1.0])
    T[:3, 3] = (500.0, -800.0, 1200.0)  # far from the origin: float32 precision matters
    cam = CameraModel.look_at((500.0, -1100.0, 1200.0), (500.0, -800.0, 1200.0), width=96,
                              height=96, fov_deg=15)
    l = _unit([0.3, -1.0, 0.4])
    sc = Scene()
    sc.add(Mesh(mesh, T, smooth=False), Lambertian(1.0))
    sc.add_light(DirectionalLight(l, np.pi))
    res = render(sc, cam)
    m = res.mask
    cos = res.normal[m].astype(float) @ l
    np.testing.assert_allclose(res.radiance[m][:, 0], np.clip(cos, 0, None), rtol=1e-5,
                               atol=1e-6)


# ----------------------------------------------------------------------------------------------
# polarization
# ----------------------------------------------------------------------------------------------
def test_crossed_polarizers_remove_specular_and_halve_diffuse(sphere_cam):
    model = CookTorrance(kd=(0.5, 0.3, 0.2), f0=0.9, alpha=0.15)
    light_pos = np.array([80.0, -250.0, 120.0])

    def scene(material, pol):
        sc = Scene()
        sc.add(Sphere(40.0, center=(0, 0, 50)), material)
        sc.add_light(PointLight(light_pos, 1e5, polarizer=pol))
        return sc

    full = render(scene(model, None), sphere_cam).radiance
    diffuse = render(scene(model.diffuse_part(), None), sphere_cam).radiance
    specular = render(scene(model.specular_part(), None), sphere_cam).radiance
    assert specular.max() > 2 * diffuse.max()  # a real highlight to remove
    np.testing.assert_allclose(diffuse + specular, full, rtol=1e-5, atol=1e-9)
    crossed = render(scene(model, 0.0), sphere_cam, polarizer=90.0).radiance
    np.testing.assert_allclose(crossed, 0.5 * diffuse, rtol=1e-5, atol=1e-9)
    parallel = render(scene(model, 30.0), sphere_cam, polarizer=30.0).radiance
    np.testing.assert_allclose(parallel, 0.5 * diffuse + specular, rtol=1e-5, atol=1e-9)
    # Malus's law in between
    at60 = render(scene(model, 10.0), sphere_cam, polarizer=70.0).radiance
    np.testing.assert_allclose(at60, 0.5 * diffuse + 0.25 * specular, rtol=1e-5, atol=1e-9)
    # an unpolarized light through the analyser: half of everything
    unpol = render(scene(model, None), sphere_cam, polarizer=45.0).radiance
    np.testing.assert_allclose(unpol, 0.5 * full, rtol=1e-5, atol=1e-9)


def test_mirror_keeps_polarization():
    center = np.array([0.0, 0.0, 30.0])
    cam = CameraModel.look_at((0.0, -400.0, 80.0), center, width=200, height=200, fov_deg=10)
    sc = Scene()
    sc.add(Sphere(25.0, center=center), Mirror(1.0))
    sc.add_light(PointLight((250.0, -200.0, 300.0), 1e5, radius=4.0, polarizer=0.0))
    base = render(sc, cam).radiance
    assert base.max() > 0
    np.testing.assert_allclose(render(sc, cam, polarizer=90.0).radiance, 0.0, atol=1e-12)
    np.testing.assert_allclose(render(sc, cam, polarizer=60.0).radiance, 0.25 * base, rtol=1e-5)


# ----------------------------------------------------------------------------------------------
# environment lighting
# ----------------------------------------------------------------------------------------------
def _sky(d):
    """A smooth sky with a bright, warm 'sun' lobe (radiance, RGB)."""
    sun = _unit([0.6, -0.5, 0.62])
    lobe = np.exp(40.0 * (d @ sun - 1.0))
    return np.stack([0.2 + 0.1 * d[:, 2] + 30 * lobe, 0.3 + 0.1 * d[:, 2] + 25 * lobe,
                     0.4 + 0.2 * np.clip(d[:, 2], 0, None) + 15 * lobe], axis=1)


def _assert_unbiased_mc(rel_by_samples):
    """Relative errors (N, ...) of Monte-Carlo renders with S and 4 S samples per pixel: the
    noise falls as 1/sqrt(S) and the mean over the N independent pixels is zero to within 4
    standard errors (plus 0.2 % for the midpoint-rule reference integral)."""
    (s1, rel1), (s4, rel4) = sorted(rel_by_samples.items())
    assert s4 == 4 * s1
    rms1, rms4 = (np.sqrt(np.mean(r ** 2)) for r in (rel1, rel4))
    assert 1.6 < rms1 / rms4 < 2.5, (rms1, rms4)
    assert abs(rel4.mean()) < 4 * rms4 / np.sqrt(len(rel4)) + 0.002, (rel4.mean(), rms4)
    return rms4


@pytest.mark.parametrize("method, rms_max", [("mis", 0.06), ("importance", 0.1),
                                              ("uniform", 0.3)])
def test_env_lit_lambertian_sphere_matches_numeric_irradiance(small_cam, method, rms_max):
    """Lambertian sphere under a sky with a sun: radiance = albedo / pi * E(n), E summed
    directly over every map pixel (EnvironmentMap.irradiance)."""
    env = EnvironmentMap.from_function(_sky, 32)
    albedo = np.array([0.7, 0.6, 0.5])
    sc = Scene(environment=env)
    sc.add(Sphere(40.0, center=(0, 0, 50)), Lambertian(albedo))
    rel = {}
    for S in (64, 256):
        res = render(sc, small_cam, env_samples=S, env_sampling=method, rng=S, shadows=False)
        m = res.mask
        expected = albedo / np.pi * env.irradiance(res.normal[m].astype(float))
        rel[S] = (res.radiance[m] / expected - 1)[:, 1]
    assert _assert_unbiased_mc(rel) < rms_max


@pytest.mark.parametrize("S", [1, 3, 5])
def test_mis_with_an_odd_sample_count_is_unbiased(small_cam, S):
    """'mis' with an odd ``env_samples`` has one more map sample than cosine samples; the
    balance heuristic must weight each strategy by its own count (weighting both as S / 2 was
    off by 40 % at S = 1 and 13 % at S = 3 on the plane). Closed forms: a Lambertian plane under
    a uniform sky of radiance L reflects albedo x L; a Lambertian sphere under the sun sky
    reflects albedo / pi x E(n), E summed over the map pixels."""
    cam = CameraModel.look_at((0.0, -120.0, 150.0), (0.0, 0.0, 0.0), width=64, height=48,
                              fov_deg=40)
    sc = Scene(environment=EnvironmentMap.constant(2.0, 16))
    sc.add(Plane((600, 600)), Lambertian(0.6))
    res = render(sc, cam, env_samples=S, rng=11 + S)
    assert res.mask.all()
    rel = res.radiance[..., 1].ravel() / (0.6 * 2.0) - 1
    se = rel.std() / np.sqrt(rel.size)
    assert abs(rel.mean()) < 4 * se + 0.002, (rel.mean(), se)

    sky = EnvironmentMap.from_function(_sky, 32)
    sc = Scene(environment=sky)
    sc.add(Sphere(40.0, center=(0, 0, 50)), Lambertian(0.7))
    res = render(sc, small_cam, env_samples=S, rng=S, shadows=False)
    m = res.mask
    rel = (res.radiance[m] / (0.7 / np.pi * sky.irradiance(res.normal[m].astype(float))) - 1)
    rel = rel[:, 1]
    se = rel.std() / np.sqrt(rel.size)
    assert abs(rel.mean()) < 4 * se + 0.004, (rel.mean(), se)


def test_env_lighting_shadowed_by_a_mesh_blocker():
    """A uniform sky over a Lambertian plane with a thin disc (mesh) hovering above it: the
    irradiance is pi L (1 - F), F the view factor from a plane element to a parallel disc of
    radius a at height h, offset s from its axis:
    F = (1 - (h^2 + s^2 - a^2) / sqrt((h^2 + s^2 + a^2)^2 - 4 a^2 s^2)) / 2."""
    env = EnvironmentMap.constant(1.0, 16)
    cam = CameraModel.look_at((0.0, -200.0, 25.0), (0.0, 0.0, 0.0), width=64, height=48,
                              fov_deg=50)
    a, h = 30.0, 30.0
    disc = trimesh.creation.cylinder(radius=a, height=0.02, sections=256)
    sc = Scene(environment=env)
    sc.add(Plane((300, 300)), Lambertian(1.0))
    sc.add(Mesh(disc, trimesh.transformations.translation_matrix([0, 0, h + 0.01])),
           Lambertian(0.0))
    rel = {}
    for S in (32, 128):
        res = render(sc, cam, env_samples=S, rng=S)
        on_plane = res.surface_index == 0
        s2 = np.sum(res.position[on_plane][:, :2] ** 2, axis=1)
        F = 0.5 * (1 - (h * h + s2 - a * a) / np.sqrt((h * h + s2 + a * a) ** 2
                                                      - 4 * a * a * s2))
        assert F.max() > 0.4 and (F > 0.1).sum() > 100  # the view includes the deep shadow
        rel[S] = res.radiance[on_plane][:, 0] / (1 - F) - 1
    assert _assert_unbiased_mc(rel) < 0.06


@pytest.mark.realdata
def test_env_lit_sphere_real_probe(shared_data, small_cam):
    env = EnvironmentMap.load(shared_data / "probes" / "uffizi.hdr").resized(32)
    sc = Scene(environment=env)
    sc.add(Sphere(40.0, center=(0, 0, 50)), Lambertian(0.5))
    rel = {}
    for S in (64, 256):
        res = render(sc, small_cam, env_samples=S, rng=S, shadows=False)
        m = res.mask
        expected = 0.5 / np.pi * env.irradiance(res.normal[m].astype(float))
        rel[S] = (res.radiance[m] / expected - 1)[:, 1]
    assert _assert_unbiased_mc(rel) < 0.1


# ----------------------------------------------------------------------------------------------
# materials and buffers
# ----------------------------------------------------------------------------------------------
def test_checkerboard_texture_material():
    cam = CameraModel.look_at((0.0, 0.0, 300.0), (0.0, 0.0, 0.0), width=80, height=80,
                              fov_deg=40, up=(0, 1, 0))

    def checker(position, uv, face_index):
        squares = (np.floor(uv[:, 0] * 8) + np.floor(uv[:, 1] * 8)) % 2
        return Lambertian(np.where(squares == 0, 0.9, 0.1))

    sc = Scene()
    sc.add(Plane((160, 160)), checker)
    sc.add_light(DirectionalLight((0, 0, 1), np.pi))
    res = render(sc, cam)
    m = res.mask
    uv = res.uv[m].astype(float)
    sq = (np.floor(uv[:, 0] * 8) + np.floor(uv[:, 1] * 8)) % 2
    np.testing.assert_allclose(res.radiance[m][:, 0], np.where(sq == 0, 0.9, 0.1), rtol=1e-6)
    # uv of the finite plane: (x / w + 1/2, y / h + 1/2)
    np.testing.assert_allclose(uv, res.position[m][:, :2] / 160 + 0.5, atol=1e-6)


def test_hemisphere_with_varying_roughness_matches_direct_brdf_evaluation():
    """SVBRDF plumbing: each pixel equals the model evaluated with that point's parameters."""
    from reconstruct.raycast import Hemisphere
    cam = CameraModel.look_at((0.0, -200.0, 150.0), (0.0, 0.0, 20.0), width=90, height=70,
                              fov_deg=30)
    light = np.array([60.0, -150.0, 200.0])

    def rough(position, uv, face_index):
        return CookTorrance(kd=0.2, f0=0.7, alpha=0.05 + 0.4 * (position[:, 0] + 50) / 100)

    sc = Scene()
    sc.add(Hemisphere(50.0), rough)
    sc.add_light(PointLight(light, 1e5))
    res = render(sc, cam, shadows=False)
    m = res.mask & (res.radiance[..., 0] > 0)
    p = res.position[m]
    n = res.normal[m].astype(float)
    o, d = cam.pixel_rays()
    wo = -d[m.ravel()]
    n = np.where((np.einsum("ij,ij->i", n, wo) < 0)[:, None], -n, n)  # inside seen: flipped
    frames = tangent_frames(n)
    wi = _unit(light - p)
    f = rough(p, None, None).evaluate(to_local(wi, frames), to_local(wo, frames))
    expected = f * np.clip(np.einsum("ij,ij->i", n, wi), 0, None)[:, None] * 1e5 / \
        np.sum((light - p) ** 2, axis=1)[:, None]
    np.testing.assert_allclose(res.radiance[m], expected, rtol=1e-4)
    assert m.sum() > 1000


def test_material_map_per_face_ids():
    box = trimesh.creation.box(extents=(60, 60, 60))
    ids = (box.face_normals[:, 0] > 0.5).astype(int)  # +x face: material 1
    cam = CameraModel.look_at((200.0, -200.0, 150.0), (0.0, 0.0, 0.0), width=80, height=80,
                              fov_deg=40)
    sc = Scene()
    sc.add(Mesh(box, smooth=False), MaterialMap([Lambertian(0.2), Lambertian(0.9)], ids))
    sc.add_light(DirectionalLight(_unit([1, -1, 1]), np.pi))
    res = render(sc, cam)
    m = res.mask
    albedo = np.where(ids[res.face_index[m]] == 1, 0.9, 0.2)
    cos = res.normal[m].astype(float) @ _unit([1, -1, 1])
    np.testing.assert_allclose(res.radiance[m][:, 0], albedo * cos, rtol=1e-5)
    assert set(np.unique(ids[res.face_index[m]])) == {0, 1}


def test_material_map_texture_ids_and_errors():
    tex = np.array([[0, 1], [1, 0]])
    mm = MaterialMap([Lambertian(0.1), Mirror()], tex)
    ids = mm.resolve_ids(np.zeros((3, 3)), np.array([[0.1, 0.1], [0.9, 0.1], [0.9, 0.9]]),
                         np.full(3, -1))
    np.testing.assert_array_equal(ids, [0, 1, 0])
    with pytest.raises(ValueError, match="id out of range"):
        MaterialMap([Lambertian(0.1)], np.array([0, 1])).resolve_ids(
            np.zeros((2, 3)), np.zeros((2, 2)), np.array([0, 1]))
    with pytest.raises(TypeError, match="materials\\[0\\]"):
        MaterialMap(["chalk"], np.array([0]))


def test_geometry_buffers_with_distortion():
    cam = CameraModel.look_at((0.0, -300.0, 50.0), (0.0, 0.0, 50.0), width=100, height=80,
                              fov_deg=25, dist=np.array([-0.2, 0.05, 0.001, -0.001, 0.0]))
    sc = Scene()
    sc.add(Sphere(40.0, center=(0, 0, 50)), Lambertian(0.5))
    sc.add(Plane(None, trimesh.transformations.translation_matrix([0, 200, 0])
                 @ trimesh.transformations.rotation_matrix(np.pi / 2, [1, 0, 0])), Lambertian(0.5))
    res = render(sc, cam)
    assert res.mask.all()
    ys, xs = np.mgrid[0:80, 0:100]
    proj = cam.project(res.position.reshape(-1, 3))
    np.testing.assert_allclose(proj, np.stack([xs.ravel(), ys.ravel()], 1), atol=1e-4)
    np.testing.assert_allclose(res.depth, cam.depth(res.position.reshape(-1, 3)).reshape(80, 100),
                               rtol=1e-6)
    assert set(np.unique(res.surface_index)) == {0, 1}
    assert np.all(res.face_index == -1)
    assert res.radiance.dtype == np.float32 and res.radiance.shape == (80, 100, 3)


def test_render_rays_matches_render(sphere_cam):
    sc = Scene()
    sc.add(Sphere(40.0, center=(0, 0, 50)), BlinnPhong(kd=0.4, ks=0.5, exponent=30))
    sc.add_light(PointLight((100.0, -200.0, 150.0), 1e5))
    res = render(sc, sphere_cam)
    o, d = sphere_cam.pixel_rays()
    L, hits = render_rays(sc, o, d)
    np.testing.assert_allclose(L.reshape(res.radiance.shape), res.radiance, rtol=1e-6)
    np.testing.assert_array_equal(hits.mask.reshape(res.mask.shape), res.mask)


def test_bad_inputs_name_the_argument(sphere_cam):
    sc = Scene()
    sc.add(Sphere(40.0), Lambertian(0.5))
    with pytest.raises(ValueError, match="PointLight.position"):
        PointLight((1.0, 2.0), 1.0)
    with pytest.raises(ValueError, match="PointLight.intensity"):
        PointLight((0, 0, 1), -1.0)
    with pytest.raises(ValueError, match="DirectionalLight.direction"):
        DirectionalLight((0, 0, 0))
    with pytest.raises(TypeError, match="camera"):
        render(sc, "cam")
    with pytest.raises(ValueError, match="env_sampling"):
        render(sc, sphere_cam, env_sampling="stratified")
    with pytest.raises(TypeError, match="rng"):
        render(sc, sphere_cam, rng=0.5)
    with pytest.raises(TypeError, match="SceneObject.material"):
        sc.add(Sphere(1.0), "gold")
    with pytest.raises(ValueError, match="Mirror.reflectance"):
        Mirror(-0.5)

    bad = Scene(lights=["lamp"])
    with pytest.raises(TypeError, match=r"scene.lights\[0\]"):
        render(bad, sphere_cam)
    with pytest.raises(ValueError, match="non-zero"):
        render_rays(sc, np.zeros((1, 3)), np.zeros((1, 3)))

    sc2 = Scene()
    sc2.add(Sphere(40.0, center=(0, 0, 50)), lambda p, uv, f: "not a brdf", name="probe")
    sc2.add_light(PointLight((0, -100, 50), 1.0))
    with pytest.raises(TypeError, match="probe"):
        render(sc2, sphere_cam)


@pytest.mark.realdata
def test_bunny_renders_with_shadows(shared_data):
    mesh = trimesh.load(shared_data / "meshes" / "bun_zipper.ply")
    T = np.eye(4)
    T[:3, :3] = 1000 * np.array([[1, 0, 0], [0, 0, -1], [0, 1, 0]])  # m -> mm, y-up -> z-up
    T[:3, 3] = -T[:3, :3] @ np.array([mesh.bounds.mean(0)[0], mesh.bounds[0][1],
                                      mesh.bounds.mean(0)[2]])
    cam = CameraModel.look_at((0, -450, 250), (0, 0, 80), width=200, height=200, fov_deg=30)
    light = np.array([200.0, -300.0, 400.0])
    sc = Scene()
    sc.add(Mesh(mesh, T), Lambertian(0.7))
    sc.add(Plane((600, 600)), Lambertian(0.3))
    sc.add_light(PointLight(light, 1e5))
    res = render(sc, cam)
    bunny = res.surface_index == 0
    assert 0.15 < bunny.mean() < 0.5
    # unshadowed pixels follow the closed form; shadowed ones are black
    p = res.position[bunny]
    n = res.normal[bunny].astype(float)
    v = light - p
    expected = 0.7 / np.pi * 1e5 * np.clip(np.einsum("ij,ij->i", n, _unit(v)), 0, None) / \
        np.sum(v * v, axis=1)
    got = res.radiance[bunny][:, 0]
    lit = got > 0
    np.testing.assert_allclose(got[lit], expected[lit], rtol=1e-4)
    assert 0.5 < lit.mean() < 0.99
    # the bunny casts a shadow on the floor behind it (away from the light)
    floor = res.surface_index == 1
    assert (res.radiance[floor][:, 0] == 0).mean() > 0.05


def test_threads_and_seeds_reproducible(small_cam):
    """Monte-Carlo frames depend on the seed and the chunking only, not on the thread count."""
    env = EnvironmentMap.from_function(_sky, 16)
    sc = Scene(environment=env)
    sc.add(Sphere(40.0, center=(0, 0, 50)), CookTorrance(kd=0.4, f0=0.5, alpha=0.3))
    kw = dict(env_samples=8, chunk=64 * 8)
    one = render(sc, small_cam, threads=1, rng=5, **kw).radiance
    two = render(sc, small_cam, threads=2, rng=5, **kw).radiance
    np.testing.assert_array_equal(one, two)
    gen = render(sc, small_cam, threads=2, rng=np.random.default_rng(5), **kw).radiance
    np.testing.assert_array_equal(one, gen)
    other = render(sc, small_cam, threads=2, rng=6, **kw).radiance
    assert np.any(other != one)


def test_kept_primary_hits_give_the_same_frames_under_other_lights(small_cam):
    """Frames of one geometry under other lights and analyser angles, started from the first
    frame's kept camera hits, equal fresh renders bit for bit in every buffer (glossy sphere,
    mirror ball, shadows on a plane, the environment); another image size is refused."""
    sc = Scene(environment=EnvironmentMap.from_function(_sky, 16))
    sc.add(Sphere(25.0, center=(-20, 0, 50)), CookTorrance(kd=0.4, f0=0.5, alpha=0.3))
    sc.add(Sphere(12.0, center=(30, -10, 40)), Mirror(0.7))
    sc.add(Plane((400.0, 400.0)), Lambertian(0.5))
    kept = PrimaryHits()
    for k, (light, pol) in enumerate([((100.0, -200.0, 150.0), None), ((-150.0, -100.0, 250.0), 0.0),
                                      ((-150.0, -100.0, 250.0), 90.0)]):
        sc.lights = [PointLight(light, 1e5, radius=10.0, polarizer=0.0)]
        kw = dict(polarizer=pol, env_samples=2, chunk=64 * 8, rng=k)
        again, fresh = render(sc, small_cam, primary=kept, **kw), render(sc, small_cam, **kw)
        for name in ("radiance", "mask", "normal", "position", "depth", "uv", "face_index",
                     "surface_index"):
            np.testing.assert_array_equal(getattr(again, name), getattr(fresh, name), err_msg=name)
    assert len(kept._chunks) == 6        # 48 rows in chunks of 8, traced by the first frame only
    with pytest.raises(ValueError, match="32 x 24"):
        render(sc, replace(small_cam, width=32, height=24), primary=kept, chunk=64 * 8)


def test_components_split_diffuse_and_specular(small_cam):
    """``components=True`` under a polarized point light through an analyser and an
    environment map: diffuse = the render of the diffuse part alone, specular = the render of
    the specular part alone (same seed, so the same environment samples); under the point light
    alone both follow the closed form I / r^2 cos(theta_i) f x the analyser's transmission
    (diffuse 1/2, specular cos^2(50 - 20 deg))."""
    model = CookTorrance(kd=(0.5, 0.3, 0.2), f0=0.8, alpha=0.2)
    env = EnvironmentMap.from_function(_sky, 16)
    light = np.array([80.0, -250.0, 120.0])

    def scene(material, environment=env):
        sc = Scene(environment=environment)
        sc.add(Sphere(40.0, center=(0, 0, 50)), material)
        sc.add_light(PointLight(light, 1e5, polarizer=20.0))
        return sc

    kw = dict(polarizer=50.0, env_samples=8, rng=2)
    res = render(scene(model), small_cam, components=True, **kw)
    diffuse_only = render(scene(model.diffuse_part()), small_cam, **kw).radiance
    specular_only = render(scene(model.specular_part()), small_cam, **kw).radiance
    m = res.mask
    np.testing.assert_allclose(res.diffuse[m], diffuse_only[m], rtol=1e-5, atol=1e-9)
    np.testing.assert_allclose(res.specular[m], specular_only[m], rtol=1e-4, atol=1e-6)
    assert np.all(res.diffuse[~m] == 0) and np.all(res.specular[~m] == 0)
    assert res.specular[m].max() > 0.1 * res.diffuse[m].max()
    assert render(scene(model), small_cam, **kw).diffuse is None

    res = render(scene(model, None), small_cam, components=True, **kw)
    m = res.mask
    p, n = res.position[m], res.normal[m].astype(float)
    v = light - p
    r2 = np.sum(v * v, axis=1)
    frames = tangent_frames(n)
    wi = to_local(v / np.sqrt(r2)[:, None], frames)
    wo = to_local(_unit(small_cam.center - p), frames)
    irradiance = (1e5 * np.clip(wi[:, 2], 0, None) / r2)[:, None]
    spec = model.specular_part().evaluate(wi, wo) * irradiance * np.cos(np.radians(30.0)) ** 2
    diff = model.diffuse_part().evaluate(wi, wo) * irradiance * 0.5
    assert spec.max() > diff.max()  # a real highlight in view
    np.testing.assert_allclose(res.specular[m], spec, rtol=2e-4, atol=1e-5 * spec.max())
    np.testing.assert_allclose(res.diffuse[m], diff, rtol=2e-4, atol=1e-5 * diff.max())


def test_docstring_examples_run():
    import doctest

    import reconstruct.render as module
    result = doctest.testmod(module)
    assert result.attempted > 0 and result.failed == 0


@pytest.mark.parametrize("dist", [None, (-0.08, 0.06, 0.0005, -0.0003, 0.0)])
def test_row_rays_are_the_pixel_rays_and_reproject_to_their_pixels(dist):
    """The renderer's cached row rays equal ``pixel_rays`` and, through the distorted lens,
    project back onto the pixel centres they were cast through (< 1e-6 px)."""
    cam = CameraModel.look_at((650.0, 0.0, 260.0), (0.0, 0.0, 55.0), width=90, height=60,
                              fov_deg=32, dist=dist)
    o, d = cam.row_rays(20, 27)
    ys, xs = np.mgrid[20:27, 0:90]
    px = np.stack([xs.ravel(), ys.ravel()], axis=1).astype(float)
    o_ref, d_ref = cam.pixel_rays(px)
    np.testing.assert_allclose(o, o_ref, atol=1e-9)
    np.testing.assert_allclose(d, d_ref, atol=1e-12)
    np.testing.assert_allclose(np.linalg.norm(d, axis=1), 1.0, atol=1e-12)
    np.testing.assert_allclose(cam.project(o + 300.0 * d), px, atol=1e-6)
    with pytest.raises(ValueError, match="rows"):
        cam.row_rays(50, 61)


def test_render_benchmark_runs_and_reports_its_figures(capsys):
    """``benchmarks/render.py`` at toy sizes: every section prints measured figures."""
    import importlib.util
    from pathlib import Path

    path = Path(__file__).resolve().parents[2] / "benchmarks" / "render.py"
    spec = importlib.util.spec_from_file_location("bench_render", path)
    bench = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(bench)
    bench.main(["--size", "48", "--env-size", "24", "--env-samples", "2", "--brdf-samples", "500",
                "--repeat", "1", "--sim-objects", "", "--table-shape", "9,9,18"])
    out = capsys.readouterr().out
    assert "load average (1 min) at start" in out and "load average (1 min) at end" in out
    assert "environment-lit sphere" in out and "s CPU" in out
    if (bench.SHARED / "meshes" / "bun_zipper.ply").is_file():   # the bunny must be timed
        assert re.search(r"bunny \(\d+ faces\) 48x48 .*\n  cold \(BVH build\) [0-9.]+ s wall", out), out
    else:
        assert "bunny: skipped" in out and "bun_zipper.ply is absent" in out
    for model in ("CookTorrance", "Lafortune", "TabulatedIsotropic", "Bivariate", "Dichromatic"):
        assert re.search(rf"{model}\s+[0-9.]+ M evals/s", out), model
