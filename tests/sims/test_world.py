"""SimWorld: rig state -> scene -> render -> sensor -> DNG, checked against its ground truth."""
from __future__ import annotations

import io

import numpy as np
import pytest
import rawpy

from reconstruct.brdf import CookTorrance, Lambertian
from reconstruct.raycast import reflect
from sims.objects import make_sphere
from sims.sensor import SensorModel
from sims.targets import SAMPLE_MATERIAL
from sims.world import (CAPTURE_KINDS, RigState, SimWorld, camera_clock, capture_targets, default_camera,
                        light_position, supersampled_camera)

SMALL = dict(width=160, height=120)


def _small_camera(**kw):
    return default_camera(SMALL["width"], SMALL["height"], fov_deg=kw.pop("fov_deg", 14.0),
                          target_mm=kw.pop("target_mm", (0.0, 0.0, 40.0)), **kw)


def test_rendered_frame_round_trips_through_dng_and_rawpy():
    """scene -> sensor -> DNG -> rawpy -> linear image within the sensor's noise of the rendered
    radiance; saturated pixels at the white level; rawpy reads the levels, CFA and white balance."""
    sensor = SensorModel.full_frame()
    world = SimWorld("sphere", camera=_small_camera(), sensor=sensor, seed=4)
    state = {"exposure_s": 0.06, "iso": 100, "fnumber": 8.0, "turntable_angle_deg": 15.0,
             "light_position_mm": tuple(light_position(20.0, 35.0)), "polarizer_angle_deg": 0.0}
    with rawpy.imread(io.BytesIO(world.frame_source(state))) as r:
        raw = r.raw_image_visible.astype(np.float64)
        black = np.array(r.black_level_per_channel)[r.raw_colors]
        white = r.white_level
        assert list(r.black_level_per_channel) == [512] * 4 and white == 16383
        desc = r.color_desc.decode()
        assert "".join(desc[c] for c in r.raw_pattern.ravel()) == "RGGB"
        wb = np.array(r.camera_whitebalance[:3])
        assert np.allclose(wb / wb[1], 1 / np.array(sensor.as_shot_neutral), rtol=1e-3)
    gt = world.ground_truth(state)
    assert gt.state.turntable_deg == 15.0 and gt.state.exposure_s == 0.06
    # the linear image: black-subtracted, white-normalised, then exposure-normalised
    linear = (raw - black) / (white - black)
    optics = dict(fnumber=8.0, focal_px=gt.camera.K[0, 0], principal_point=tuple(gt.camera.K[:2, 2]))
    per_radiance = sensor.mean_electrons(np.ones_like(gt.radiance), 0.06, **optics)
    est = (linear * (white - black) * sensor.e_per_dn(100) - sensor.dark_current_e_s * 0.06) / per_radiance
    truth = sensor.mosaic(gt.radiance)
    # noise bound from the sensor model (shot + dark + read + quantisation), per pixel
    sigma = gt.expected.sigma_dn * sensor.e_per_dn(100) / per_radiance
    ok = ~gt.expected.saturated
    z = (est - truth)[ok] / sigma[ok]
    assert np.abs(z).max() < 5.5
    assert abs(z.mean()) < 5 / np.sqrt(z.size) and abs(z.std() - 1) < 0.05
    # the object is really there (not a black frame) and clips where the model says it must
    on_object = gt.buffers.surface_index == 0
    assert on_object.sum() > 3000 and np.median(linear[on_object]) > 0.15  # half is in shadow
    sure = gt.expected.mean_dn - 5 * gt.expected.sigma_dn > white
    assert sure.sum() > 100 and np.all(raw[sure] == white)


def test_rig_state_reads_the_lab_and_nested_forms():
    lab = RigState.from_state({"turntable_angle_deg": 30.0, "light_position_mm": (1.0, 2.0, 3.0),
                               "polarizer_angle_deg": 90.0, "exposure_s": 0.02, "iso": 200,
                               "fnumber": 5.6, "capture_number": 7})
    assert lab == RigState(30.0, (1.0, 2.0, 3.0), 90.0, 0.02, 200.0, 5.6)
    nested = RigState.from_state({"turntable": {"angle_deg": -10}, "light": {"position_mm": [0, 0, 500]},
                                  "polarizer": {"angle_deg": 45}})
    assert (nested.turntable_deg, nested.light_position_mm, nested.polarizer_deg) == (-10.0, (0.0, 0.0, 500.0), 45.0)
    assert RigState.from_state(None) == RigState() and RigState().polarizer_deg is None
    with pytest.raises(ValueError, match="exposure_s"):
        RigState.from_state({"exposure_s": 0})
    with pytest.raises(ValueError, match="light_position_mm"):
        RigState.from_state({"light_position_mm": (1, 2)})
    with pytest.raises(ValueError, match="turntable angle"):
        RigState.from_state({"turntable_angle_deg": "north"})


def test_noise_is_seeded_and_fresh_per_frame():
    def raws(seed):
        w = SimWorld("sphere", camera=_small_camera(), seed=seed)
        out = []
        for _ in range(2):
            with rawpy.imread(io.BytesIO(w.frame_source({"exposure_s": 0.01}))) as r:
                out.append(r.raw_image_visible.copy())
        return out
    a1, a2 = raws(3)
    b1, _ = raws(3)
    assert np.array_equal(a1, b1)          # same seed, same first frame
    assert not np.array_equal(a1, a2)      # but every frame draws new noise


def test_crossed_polarizers_leave_half_the_diffuse_part():
    """State's analyser angle reaches the renderer: crossed with the lamp's polarizer, the glossy
    sphere shows exactly half its diffuse (body) reflection; parallel, all of the specular too."""
    glossy = CookTorrance(kd=(0.5, 0.4, 0.3), f0=0.04, alpha=0.1)
    cam = _small_camera()
    state = {"light_position_mm": tuple(light_position(10.0, 30.0))}
    world = SimWorld(make_sphere(material=glossy, marker_dirs=()), camera=cam, light_polarizer_deg=0.0)
    crossed = world.radiance({**state, "polarizer_angle_deg": 90.0})
    parallel = world.radiance({**state, "polarizer_angle_deg": 0.0})
    diffuse_only = SimWorld(make_sphere(material=Lambertian((0.5, 0.4, 0.3)), marker_dirs=()),
                            camera=cam).radiance(state)
    mask = world.ground_truth(state).buffers.surface_index == 0
    assert np.allclose(crossed[mask], 0.5 * diffuse_only[mask], rtol=1e-5, atol=1e-7)
    spec = parallel[mask] - crossed[mask]
    assert spec.max() > 0.05 and spec.min() >= -1e-6
    # the ground truth's split: crossed keeps no specular part, parallel all of it
    for pol, frame in ((90.0, crossed), (0.0, parallel)):
        gt = world.ground_truth({**state, "polarizer_angle_deg": pol})
        assert np.allclose(gt.radiance, frame)
        assert np.allclose(gt.diffuse[mask] + gt.specular[mask], frame[mask], rtol=1e-5, atol=1e-7)
        assert np.allclose(gt.diffuse[mask], 0.5 * diffuse_only[mask], rtol=1e-5, atol=1e-7)
    assert np.abs(world.ground_truth({**state, "polarizer_angle_deg": 90.0}).specular).max() < 1e-7


def test_capture_kinds_build_their_scenes():
    cam = _small_camera()
    spheres = SimWorld.for_capture("spheres", camera=cam)
    names = [o.name for o in spheres.scene().objects]
    assert sum(n.startswith("steel_sphere") for n in names) == 6 and any(n.startswith("sphere:") for n in names)
    dark = SimWorld.for_capture("dark", camera=cam, sensor=SensorModel.compact(), seed=1)
    with rawpy.imread(io.BytesIO(dark.frame_source({"exposure_s": 1.0, "iso": 100}))) as r:
        d = r.raw_image_visible.astype(float)
    s = SensorModel.compact()
    assert d.mean() - s.black_level == pytest.approx(s.dark_current_e_s / s.e_per_dn(100), abs=0.1)
    flat = SimWorld.for_capture("flat", camera=cam, sensor=SensorModel.compact(vignetting="none"))
    assert np.all(flat.radiance() == 0.4)
    with pytest.raises(ValueError, match="capture kind"):
        SimWorld.for_capture("moon")
    assert "mirror_probe" in CAPTURE_KINDS


def test_one_vocabulary_of_scene_targets():
    """Every scene target a plan can name is a scene the simulated lab stages under that same
    name (no translation table), and ``gonio sim render --scene`` offers exactly these scenes."""
    from capture.cli.sim import SCENES
    from capture.plan import CALIBRATION_KINDS, SCENE_TARGETS

    assert set(CALIBRATION_KINDS) < set(SCENE_TARGETS) <= set(CAPTURE_KINDS)
    assert SCENES == CAPTURE_KINDS
    assert not hasattr(SimWorld, "TARGET_KINDS")


def test_probe_capture_reflects_the_environment_in_the_chrome_ball():
    from sims.targets import procedural_sky
    env = procedural_sky(height=64)
    cam = default_camera(120, 90, fov_deg=8.0, target_mm=(0.0, 0.0, 25.4))
    world = SimWorld.for_capture("mirror_probe", camera=cam, environment=env, supersample=1)  # per ray
    gt = world.ground_truth({})
    m = gt.buffers.mask
    assert m.sum() > 2000 and np.all(gt.buffers.surface_index[m] == 0)
    # each pixel on the ball sees 0.65 x the environment along the mirrored viewing ray
    _, d = cam.pixel_rays(np.argwhere(m)[:, ::-1].astype(float))
    r = reflect(d, gt.buffers.normal[m].astype(np.float64))
    expect = 0.65 * env.lookup(r)
    inner = (gt.buffers.normal[m] @ -d.T).diagonal() > 0.3  # away from the grazing rim
    assert np.allclose(gt.radiance[m][inner], expect[inner], rtol=0.02, atol=0.01)


def test_supersampled_camera_keeps_the_geometry():
    cam = default_camera(64, 48)
    hi = supersampled_camera(cam, 3)
    pts = np.array([[0.0, 0.0, 40.0], [30.0, -20.0, 70.0]])
    assert np.allclose(hi.project(pts), 3 * (cam.project(pts) + 0.5) - 0.5, atol=1e-9)
    assert (hi.width, hi.height) == (192, 144)


def test_bad_world_arguments_are_named():
    with pytest.raises(TypeError, match="object"):
        SimWorld(42)
    with pytest.raises(ValueError, match="supersample"):
        SimWorld(None, supersample=0)
    with pytest.raises(TypeError, match="targets"):
        SimWorld(None, targets=["board"])
    with pytest.raises(ValueError, match="elevation"):
        light_position(0.0, 120.0)


def test_the_same_captures_give_the_same_bytes_stamped_by_the_camera_clock():
    """Two worlds of one seed give byte-identical DNGs for the same captures in the same order (the
    sensor noise is the seed's; the DateTime is the simulated camera's clock, not the wall clock)."""
    import tifffile
    state = {"exposure_s": 0.01, "iso": 100, "fnumber": 8.0, "turntable_angle_deg": 30.0}
    first, second = (SimWorld("sphere", camera=_small_camera(), seed=3) for _ in range(2))
    a = [first.frame_source({**state, "capture_number": n}) for n in (1, 2)]
    b = [second.frame_source({**state, "capture_number": n}) for n in (1, 2)]
    assert a == b and a[0] != a[1]   # the second draws fresh noise
    with tifffile.TiffFile(io.BytesIO(a[1])) as tif:
        assert tif.pages[0].tags["DateTime"].value == "2026:01:01 00:00:02"
    assert camera_clock({"capture_number": 61}) == "2026:01:01 00:01:01"
    with rawpy.imread(io.BytesIO(a[0])) as r:
        assert r.raw_image_visible.shape == (_small_camera().height, _small_camera().width)


def test_passive_capture_lights_the_object_by_the_environment_only():
    """Under a uniform environment of radiance L and no lamp, an unshadowed Lambertian surface of
    albedo a has radiance a * L (irradiance pi L times a / pi), whatever its normal."""
    from reconstruct.envmap import EnvironmentMap
    obj = make_sphere(material=Lambertian(0.6), marker_dirs=())
    world = SimWorld.for_capture("passive", obj, camera=_small_camera(), environment=EnvironmentMap.constant(0.5),
                                 env_samples=64)
    assert world.scene().lights == []
    gt = world.ground_truth({})
    up = gt.buffers.surface_index == 0  # no platter, and a convex sphere never shadows itself
    assert up.sum() > 1000
    # Monte-Carlo over 64 samples per pixel: the mean over >1000 pixels within 2 %
    assert gt.radiance[up].mean() == pytest.approx(0.3, rel=0.02)


def test_set_scene_follows_the_runner_targets_and_comes_back():
    world = SimWorld("sphere", camera=_small_camera(), sensor=SensorModel.compact(), seed=2)
    names = lambda: [o.name for o in world.scene().objects]  # noqa: E731
    home = names()
    world.prepare_target("checkerboard")
    assert names()[0] == "charucotarget" and not any(n.startswith("sphere:") for n in names())
    world.prepare_target("mirror_probe")
    assert world.environment is not None and world.scene().lights == []
    world.prepare_target("dark")
    with rawpy.imread(io.BytesIO(world.frame_source({"exposure_s": 0.01}))) as r:
        assert r.raw_image_visible.mean() < SensorModel.compact().black_level + 2
    world.set_scene("object")
    assert names() == home and world.environment is None and len(world.scene().lights) == 1
    with pytest.raises(ValueError, match="capture kind"):
        world.set_scene("tripod")


def test_the_sample_sphere_scene_is_the_sphere_the_lab_states_under_the_room_alone():
    """``passive_sphere``: one homogeneous sphere where :func:`capture_targets` says it is, lit by the
    room alone (no lamp, no cloth) at the environment sample count a glossy lobe needs; the world's
    own count comes back with the object."""
    world = SimWorld("sphere", camera=_small_camera(), sensor=SensorModel.compact(), seed=2)
    world.prepare_target("passive_sphere")
    (ball,) = world.scene().objects
    stated = capture_targets()
    assert ball.name == "sample_sphere" and ball.surface.radius == stated["sample_sphere_radius_mm"] == 30.0
    assert np.allclose(ball.surface.center, stated["sample_sphere_centre_mm"])
    assert ball.material is SAMPLE_MATERIAL and world.scene().lights == [] and world.environment is not None
    assert world.env_samples == SimWorld.KIND_ENV_SAMPLES["passive_sphere"] > 32
    world.set_scene("object")
    assert world.env_samples == 32 and len(world.scene().lights) == 1


def test_a_bracket_renders_once_and_gives_the_bytes_of_fresh_renders(monkeypatch):
    """Frames differing only in exposure, ISO or aperture share one render (the radiance does not
    depend on them); their DNGs are byte for byte those of a world that renders every frame
    afresh, and a moved light, a turned polarizer or a changed scene renders again."""
    import sims.world as world_module
    renders = []
    real_render = world_module.render
    monkeypatch.setattr(world_module, "render", lambda *a, **k: renders.append(1) or real_render(*a, **k))
    base = {"turntable_angle_deg": 30.0, "polarizer_angle_deg": 0.0, "fnumber": 8.0, "iso": 100}
    states = [{**base, "exposure_s": 0.01}, {**base, "exposure_s": 0.04, "iso": 200},
              {**base, "exposure_s": 0.01, "polarizer_angle_deg": 90.0},
              {**base, "exposure_s": 0.01, "light_position_mm": tuple(light_position(40.0, 30.0))}]
    cached, fresh = (SimWorld("sphere", camera=_small_camera(), seed=5) for _ in range(2))
    a = [cached.frame_source(s) for s in states]
    assert len(renders) == 3                 # the second frame reused the first one's render
    b = []
    for s in states:
        fresh._last_radiance = None          # forget it: every frame rendered afresh
        b.append(fresh.frame_source(s))
    assert len(renders) == 7 and a == b
    cached.set_scene("gray_card")
    cached.frame_source(states[-1])
    assert len(renders) == 8                 # same rig state, new scene: rendered again
