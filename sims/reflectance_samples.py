"""Synthetic lumitexels of known materials: the experiment at the end of Lensch et al. 2003, Sec. 11.

Texels with random normals are seen from a few fixed camera directions and lit from random
directions, a share of them placed near the mirror direction of the view (so that the specular
lobes are sampled and their exponents identifiable); each sample's reflectance f_r cos(theta_i)
gets uniform multiplicative noise. Everything is returned in the layout of
:class:`reconstruct.lumitexels.Lumitexels` (samples sorted by texel, local frames from
:func:`reconstruct.frames.tangent_frames` of the normals).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from reconstruct.brdf import BRDF, Lafortune
from reconstruct.camera import CameraModel
from reconstruct.frames import normalize, tangent_frames, to_local
from reconstruct.lensch.lafortune_fit import fit_geometry, lobe_geometry
from reconstruct.lensch.projection import cluster_errors
from reconstruct.lumitexels import View
from reconstruct.render import PointLight, Scene, render

from .objects import turntable_pose
from .sensor import SensorModel


def paper_phong_materials(kd=(0.15, 0.3, 0.1), exponents=(36.2, 42.2, 48.2, 54.2, 60.2)):
    """The paper's five materials: one diffuse colour, modified-Phong lobes of the given exponents,
    C_z = -C_x = ((N + 2) / 2 pi)^(1/N) (unit specular albedo). ``kd`` is the modified-Phong
    diffuse albedo, i.e. our ``rho_d`` (pi x the paper's rho_d)."""
    return tuple(Lafortune.phong(rho_d=kd, rho_s=1.0, exponent=N) for N in exponents)


@dataclass(frozen=True)
class SyntheticSamples:
    """Reflectance samples of texels with known material and normal.

    ``texel`` (S,), ``wi`` / ``wo`` (S, 3) local unit directions, ``reflectance`` (S, 3) =
    f_r cos(theta_i) with noise, ``clean`` (S, 3) without; per texel ``normal`` (T, 3) (world) and
    ``material`` (T,) the index into the materials.
    """

    texel: np.ndarray
    wi: np.ndarray
    wo: np.ndarray
    reflectance: np.ndarray
    clean: np.ndarray
    normal: np.ndarray
    material: np.ndarray


def _random_hemisphere(rng, n, axis, min_cos):
    """Uniform directions (n, 3) within acos(min_cos) of the unit ``axis`` rows (n, 3)."""
    cz = rng.uniform(min_cos, 1.0, n)
    phi = rng.uniform(0, 2 * np.pi, n)
    s = np.sqrt(1 - cz ** 2)
    local = np.stack([s * np.cos(phi), s * np.sin(phi), cz], axis=1)
    return np.einsum("nji,nj->ni", tangent_frames(axis), local)


def synthetic_samples(materials: tuple[BRDF, ...], n_texels: int, *, samples_per_texel: float = 11,
                      n_views: int = 5, mirror_fraction: float = 0.35, mirror_spread_deg: float = 6.0,
                      noise: float = 0.05, rng=0) -> SyntheticSamples:
    """Texels of the given materials (equal shares, random order) and their noisy samples.

    Parameters
    ----------
    materials : tuple of BRDF
    n_texels : int
    samples_per_texel : float
        Mean samples per texel (each texel gets 7..15 for the default 11).
    n_views : int
        Camera directions (elevation 50 deg, evenly spaced azimuths, world frame).
    mirror_fraction : float
        Share of samples whose light is placed near the mirror direction of the view about the
        normal (Gaussian spread ``mirror_spread_deg``); the rest are uniform over the hemisphere.
    noise : float
        Uniform multiplicative noise: reflectance * (1 + U(-noise, noise)).
    rng : int or numpy.random.Generator
    """
    rng = np.random.default_rng(rng)
    if n_texels < len(materials):
        raise ValueError(f"n_texels must be >= the number of materials, got {n_texels}")
    material = rng.permutation(np.arange(n_texels) % len(materials))
    az = 2 * np.pi * np.arange(n_views) / n_views
    el = np.radians(50.0)
    views = np.stack([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.full(n_views, np.sin(el))], 1)
    up = np.tile([0.0, 0.0, 1.0], (n_texels, 1))
    normal = _random_hemisphere(rng, n_texels, up, np.cos(np.radians(40)))
    spread = max(int(round(samples_per_texel)) - 4, 0)
    counts = rng.integers(samples_per_texel - spread, samples_per_texel + spread + 1, n_texels)
    texel = np.repeat(np.arange(n_texels), counts)
    S = len(texel)
    frames = tangent_frames(normal)[texel]
    # a visible view per sample (redrawn where the view is behind the texel)
    wo = to_local(views[rng.integers(0, n_views, S)], frames)
    bad = wo[:, 2] < 0.1
    while bad.any():
        wo[bad] = to_local(views[rng.integers(0, n_views, bad.sum())], frames[bad])
        bad = wo[:, 2] < 0.1
    z = np.tile([0.0, 0.0, 1.0], (S, 1))
    wi = _random_hemisphere(rng, S, z, 0.1)
    near = rng.random(S) < mirror_fraction
    mirror = wo[near] * [-1, -1, 1]
    jitter = normalize(mirror + np.radians(mirror_spread_deg) * rng.normal(size=mirror.shape))
    wi[near] = np.where(jitter[:, 2:3] > 0.1, jitter, mirror)
    clean = np.empty((S, 3))
    for k, m in enumerate(materials):
        sel = material[texel] == k
        clean[sel] = m.evaluate(wi[sel], wo[sel]) * wi[sel, 2:3]
    noisy = clean * (1 + rng.uniform(-noise, noise, clean.shape))
    return SyntheticSamples(texel=texel, wi=wi, wo=wo, reflectance=noisy, clean=clean,
                            normal=normal, material=material)


def noisy_views(obj, poses: list[tuple[float, np.ndarray]], camera, *, light_intensity: float = 3.6e5,
                sensor=None, headroom: float = 0.8, rng=0, progress=None) -> list:
    """Render ``obj`` under point lights and take each frame with a sensor's noise.

    Parameters
    ----------
    obj : GroundTruthObject
        The object (its ``parts`` are rendered).
    poses : list of (turntable angle in degrees, light position (3,) world mm)
        One frame per entry.
    camera : reconstruct.camera.CameraModel
        The fixed camera (world frame).
    light_intensity : float
        Radiant intensity of the light (per sr, the renderer's units).
    sensor : sims.sensor.SensorModel, optional
        Whose full well and read noise set the noise (default: the full-frame body). Each frame
        is exposed so that its brightest 0.1 % of object pixels sit at ``headroom`` x full well
        (an HDR capture); electrons get Poisson shot noise and Gaussian read noise, pixels at the
        full well are marked invalid (saturated).
    rng : int or numpy.random.Generator
    progress : callable, optional
        ``progress(done, total)`` after each frame.

    Returns
    -------
    list of reconstruct.lumitexels.View
        Radiance in the renderer's units, object pose = the turntable pose.
    """
    sensor = SensorModel() if sensor is None else sensor
    rng = np.random.default_rng(rng)
    views = []
    for k, (angle, light) in enumerate(poses):
        scene = Scene(objects=obj.scene_objects(angle))
        scene.add_light(PointLight(np.asarray(light, float), light_intensity))
        res = render(scene, camera, rng=int(rng.integers(1 << 31)))
        rad = res.radiance.astype(np.float64)
        bright = np.percentile(rad[res.mask], 99.9) if res.mask.any() else 1.0
        gain = headroom * sensor.full_well_e / max(bright, 1e-12)  # electrons per radiance unit
        e = rng.poisson(rad * gain) + rng.normal(0.0, sensor.read_noise_e, rad.shape)
        saturated = (rad * gain >= sensor.full_well_e).any(axis=2)
        e = np.minimum(e, sensor.full_well_e)
        views.append(View(camera=camera, radiance=(e / gain).astype(np.float32),
                          light_position=np.asarray(light, float), light_intensity=light_intensity,
                          object_to_world=turntable_pose(angle), valid=res.mask & ~saturated))
        if progress is not None:
            progress(k + 1, len(poses))
    return views


def turntable_capture(obj, *, width: int = 160, n_angles: int = 6, light_distance_mm: float = 600.0,
                      rng=0, progress=None) -> tuple[list, list]:
    """Noisy views of ``obj`` for reflectance fitting: a fixed camera on the +x side, the turntable
    at ``n_angles`` angles, six lights per angle (azimuths -50..70 deg, elevations 10..50 deg
    about the object's centre), plus two held-out frames at other angles and light positions.

    Returns (fitting views, held-out views), each a list of ``reconstruct.lumitexels.View``.
    The camera is ``width`` x 3/4 ``width`` pixels framing the object (11 deg field of view).
    """
    centre = np.array([0.0, 0.0, obj.height_mm / 2])
    camera = CameraModel.look_at(centre + [500.0, 0.0, 210.0], centre, width=width,
                                 height=width * 3 // 4, fov_deg=11.0)

    def light(az, el):
        a, e = np.radians(az), np.radians(el)
        return centre + light_distance_mm * np.array([np.cos(e) * np.cos(a), np.cos(e) * np.sin(a),
                                                      np.sin(e)])
    lights = [(-50, 20), (-20, 50), (0, 25), (25, 10), (45, 45), (70, 25)]
    angles = np.arange(n_angles) * 360.0 / n_angles
    poses = [(a, light(az, el)) for a in angles for az, el in lights]
    held = [(angles[0] + 180.0 / n_angles, light(10, 35)), (angles[n_angles // 2] + 180.0 / n_angles,
                                                             light(-35, 15))]
    views = noisy_views(obj, poses + held, camera, rng=rng, progress=progress)
    return views[:len(poses)], views[len(poses):]


@dataclass(frozen=True)
class AssignedFit:
    """The reference a clustering is judged against: each material's Lafortune parameters fitted
    to the samples of its true texels, ``params`` (K, 3, P) per channel, and the Eq. 10 labels
    (T,) those parameters give every texel."""

    params: np.ndarray
    labels: np.ndarray


def fit_true_assignment(samples: SyntheticSamples, *, n_lobes: int = 1,
                        noise: str = "relative") -> AssignedFit:
    """Fit each material on the texels truly made of it (Lensch Sec. 6), then label every texel
    by its least Eq. 6 error under those fits (relative under ``noise="relative"``, as
    :func:`~reconstruct.lensch.fit_svbrdf` labels): what a clustering that found the true assignment
    would give, noise included (the paper's accuracy claim is met when a fit is this close)."""
    t, z = lobe_geometry(samples.wi, samples.wo)
    w = np.ones(len(t))
    of = samples.material[samples.texel]
    params = np.stack([fit_geometry(t[of == k], z[of == k], samples.wi[of == k, 2],
                                    samples.reflectance[of == k], w[of == k], n_lobes=n_lobes,
                                    noise=noise).channel_params
                       for k in range(int(samples.material.max()) + 1)])
    errors = cluster_errors(t, z, samples.wi[:, 2], samples.reflectance, w, samples.texel,
                            len(samples.material), params, relative=noise == "relative")
    return AssignedFit(params=params, labels=errors.argmin(axis=0))
