"""Physically based direct-lighting renderer: point/directional/environment lights, shadows,
SVBRDF materials, mirrors, linear polarizers, and geometry buffers.

Frames and units: world = turntable frame (mm, +z up); the camera is a
:class:`reconstruct.camera.CameraModel`. Radiance is linear RGB in the lights' units: a point
light of radiant intensity ``I`` [X/sr] at distance ``r`` [mm] gives irradiance ``I / r^2``
[X/mm^2] and radiance ``f_r * I / r^2 * cos(theta_i)`` [X/(mm^2 sr)]; a directional light's
``irradiance`` and an environment map's radiance are used as given, so one scene should use one
unit throughout.

Light transport: direct lighting from every light (shadow rays when ``shadows``), Monte-Carlo
environment lighting (by default multiple importance sampling: the map's luminance x solid angle
combined with cosine-weighted hemisphere sampling, balance heuristic), and perfect mirrors that
follow reflection rays up to ``max_bounces`` (seeing surfaces, the environment, and spherical
point lights with ``radius > 0``). Inter-reflections between non-mirror surfaces are not
simulated. Surfaces are two-sided: seen from the back, the normals are flipped towards the
viewer for shading.

Polarization (ideal linear polarizers, angles in degrees in a common reference): a light with
``polarizer`` emits light linearly polarized at that angle (its ``intensity`` is what leaves
the polarizer); an analyser on the lens (``render(..., polarizer=beta)``) passes
``cos^2(alpha - beta)`` of the specular (interface) reflection of light polarized at
``alpha`` — specular reflection keeps the polarization — and half of everything depolarized:
diffuse (body) reflection, unpolarized lights, the environment. The split comes from the
models' ``diffuse_part()`` / ``specular_part()``.
"""
from __future__ import annotations

import os
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field, replace
from typing import Callable, Sequence

import numpy as np

from .brdf.base import BRDF
from .camera import CameraModel
from .envmap import EnvironmentMap
from .frames import tangent_frames, to_local
from .raycast import (OFFSET_EPS, Hits, Surface, _check_rays, _first_hits, _occluded,
                      offset_origins, reflect, scene_scale)

#: Rays processed together: bounds memory (~1 kB per ray in flight) and keeps arrays small
#: enough (a few MB) for the allocator to reuse them instead of page-faulting fresh blocks,
#: which made whole-frame passes ~3x slower. 2^16 measured best (2026-11, 2 cores: the 1 MP
#: bunny and the default sim frame take 10-25 % less CPU than with 2^17, 2^15 or 2^18).
DEFAULT_CHUNK = 1 << 16


# ----------------------------------------------------------------------------------------------
# materials
# ----------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class Mirror:
    """A perfect specular reflector (delta BRDF): radiance = ``reflectance`` x radiance arriving
    along the mirrored viewing ray. Polarization-preserving.

    Parameters
    ----------
    reflectance : float or (3,)
        Fraction reflected, RGB, in [0, 1] (chrome ~0.6-0.8; an ideal mirror 1).
    """

    reflectance: object = 1.0

    def __post_init__(self):
        r = np.asarray(self.reflectance, dtype=np.float64)
        if r.shape not in ((), (3,)) or not np.all(np.isfinite(r)) or np.any(r < 0):
            raise ValueError(f"Mirror.reflectance must be a scalar or RGB triple >= 0, got "
                             f"{self.reflectance!r}")


@dataclass(frozen=True, eq=False)
class MaterialMap:
    """Several materials on one surface, chosen per hit point by an id.

    Parameters
    ----------
    materials : sequence of materials
        Each a BRDF, a :class:`Mirror` or a per-point callable (see :data:`Material`).
    ids : ndarray of shape (F,) int, ndarray of shape (h, w) int, or callable
        Per-face ids (meshes; indexed by ``face_index``); or an id texture looked up at the hit's
        ``uv`` (nearest texel; column = u * w, row = v * h, row 0 at v = 0); or
        ``ids(position (N, 3), uv (N, 2), face_index (N,)) -> (N,) int``.
    """

    materials: Sequence
    ids: object

    def __post_init__(self):
        if len(self.materials) == 0:
            raise ValueError("MaterialMap.materials is empty")
        for k, m in enumerate(self.materials):
            if isinstance(m, MaterialMap) or not (isinstance(m, (BRDF, Mirror)) or callable(m)):
                raise TypeError(f"MaterialMap.materials[{k}] must be a BRDF, Mirror or callable, "
                                f"got {type(m).__name__}")
        if not callable(self.ids):
            ids = np.asarray(self.ids)
            if ids.ndim not in (1, 2) or not np.issubdtype(ids.dtype, np.integer):
                raise ValueError("MaterialMap.ids must be an (F,) per-face or (h, w) texture "
                                 f"integer array, or a callable; got {ids.dtype} {ids.shape}")
            object.__setattr__(self, "ids", ids)

    def resolve_ids(self, position, uv, face_index) -> np.ndarray:
        """Material index of each hit point (N,)."""
        if callable(self.ids):
            ids = np.asarray(self.ids(position, uv, face_index))
        elif self.ids.ndim == 1:
            if np.any(face_index < 0) or np.any(face_index >= len(self.ids)):
                raise ValueError("MaterialMap.ids is per-face but a hit has face_index outside "
                                 f"[0, {len(self.ids)}) (is the surface a mesh?)")
            ids = self.ids[face_index]
        else:
            if np.any(~np.isfinite(uv)):
                raise ValueError("MaterialMap.ids is a texture but the surface has no uv")
            h, w = self.ids.shape
            col = np.clip((uv[:, 0] * w).astype(np.int64), 0, w - 1)
            row = np.clip((uv[:, 1] * h).astype(np.int64), 0, h - 1)
            ids = self.ids[row, col]
        if ids.shape != (len(position),):
            raise ValueError(f"MaterialMap ids must have shape ({len(position)},), got {ids.shape}")
        if np.any(ids < 0) or np.any(ids >= len(self.materials)):
            raise ValueError(f"MaterialMap id out of range [0, {len(self.materials)}): "
                             f"{ids.min()}..{ids.max()}")
        return ids


#: A surface's material: a BRDF (uniform), a :class:`Mirror`, a :class:`MaterialMap`, or a
#: callable ``material(position (N, 3) mm world, uv (N, 2), face_index (N,)) -> BRDF`` whose
#: parameters have a leading (N,) axis (spatially varying BRDF).
Material = BRDF | Mirror | MaterialMap | Callable


# ----------------------------------------------------------------------------------------------
# lights and scene
# ----------------------------------------------------------------------------------------------
def _rgb3(name, value) -> np.ndarray:
    a = np.broadcast_to(np.asarray(value, dtype=np.float64), (3,)).copy() \
        if np.ndim(value) in (0, 1) and np.size(value) in (1, 3) else None
    if a is None or not np.all(np.isfinite(a)) or np.any(a < 0):
        raise ValueError(f"{name} must be a scalar or RGB triple of finite values >= 0, got "
                         f"{value!r}")
    return a


def _angle(name, value):
    if value is None:
        return None
    if not np.isfinite(value):
        raise ValueError(f"{name} must be an angle in degrees or None, got {value!r}")
    return float(value)


@dataclass(frozen=True, eq=False)
class PointLight:
    """An isotropic point light (optionally a small sphere, for mirror highlights).

    Parameters
    ----------
    position : (3,)
        World frame, mm.
    intensity : float or (3,)
        Radiant intensity (RGB, per sr) leaving the light (after its polarizer, if any).
    radius : float
        Radius (mm) of the spherical emitter seen in mirrors, with uniform radiance
        ``intensity / (pi radius^2)``; 0: a true point (invisible in mirrors). Diffuse and glossy
        shading always treat the light as a point with inverse-square falloff.
    polarizer : float or None
        Angle (degrees) of a linear polarizer in front of the light; None: unpolarized.
    """

    position: object
    intensity: object = 1.0
    radius: float = 0.0
    polarizer: float | None = None

    def __post_init__(self):
        p = np.asarray(self.position, dtype=np.float64)
        if p.shape != (3,) or not np.all(np.isfinite(p)):
            raise ValueError(f"PointLight.position must be a finite 3-vector in mm, got "
                             f"{self.position!r}")
        object.__setattr__(self, "position", p)
        object.__setattr__(self, "intensity", _rgb3("PointLight.intensity", self.intensity))
        if not np.isfinite(self.radius) or self.radius < 0:
            raise ValueError(f"PointLight.radius must be >= 0 mm, got {self.radius!r}")
        object.__setattr__(self, "polarizer", _angle("PointLight.polarizer", self.polarizer))


@dataclass(frozen=True, eq=False)
class DirectionalLight:
    """A distant light.

    Parameters
    ----------
    direction : (3,)
        World direction from the scene towards the light (normalised here).
    irradiance : float or (3,)
        Irradiance (RGB) on a surface facing the light.
    polarizer : float or None
        Linear polarizer angle (degrees) on the light; None: unpolarized.
    """

    direction: object
    irradiance: object = 1.0
    polarizer: float | None = None

    def __post_init__(self):
        d = np.asarray(self.direction, dtype=np.float64)
        if d.shape != (3,) or not np.all(np.isfinite(d)) or np.linalg.norm(d) == 0:
            raise ValueError(f"DirectionalLight.direction must be a non-zero 3-vector, got "
                             f"{self.direction!r}")
        object.__setattr__(self, "direction", d / np.linalg.norm(d))
        object.__setattr__(self, "irradiance", _rgb3("DirectionalLight.irradiance",
                                                     self.irradiance))
        object.__setattr__(self, "polarizer", _angle("DirectionalLight.polarizer",
                                                     self.polarizer))


@dataclass(eq=False)
class SceneObject:
    """A placed surface and its material (see :data:`Material`)."""

    surface: Surface
    material: object
    name: str = ""

    def __post_init__(self):
        if not isinstance(self.surface, Surface):
            raise TypeError(f"SceneObject.surface must be a raycast.Surface, got "
                            f"{type(self.surface).__name__}")
        m = self.material
        if not (isinstance(m, (BRDF, Mirror, MaterialMap)) or callable(m)):
            raise TypeError(f"SceneObject.material of {self.name or 'object'} must be a BRDF, "
                            f"Mirror, MaterialMap or callable, got {type(m).__name__}")


@dataclass(eq=False)
class Scene:
    """What the renderer draws: objects, lights and an optional environment map.

    ``surface_index`` in the geometry buffers indexes ``objects``.
    """

    objects: list[SceneObject] = field(default_factory=list)
    lights: list = field(default_factory=list)
    environment: EnvironmentMap | None = None

    def add(self, surface: Surface, material, name: str = "") -> SceneObject:
        """Append a surface with its material; returns the new object."""
        obj = SceneObject(surface, material, name)
        self.objects.append(obj)
        return obj

    def add_light(self, light) -> None:
        if not isinstance(light, (PointLight, DirectionalLight)):
            raise TypeError(f"light must be a PointLight or DirectionalLight, got "
                            f"{type(light).__name__}")
        self.lights.append(light)

    @property
    def surfaces(self) -> list[Surface]:
        return [o.surface for o in self.objects]


# ----------------------------------------------------------------------------------------------
# results
# ----------------------------------------------------------------------------------------------
@dataclass(eq=False)
class RenderResult:
    """A rendered frame and its geometry buffers (H x W).

    Attributes
    ----------
    radiance : ndarray of shape (H, W, 3), float32
        Linear radiance, RGB (units: see module docstring), after the analyser if any.
    mask : ndarray of shape (H, W), bool
        Pixels whose camera ray hit a surface.
    normal : ndarray of shape (H, W, 3), float32
        Unit shading normal, world frame, outward as stored (not flipped); zero off the mask.
    position : ndarray of shape (H, W, 3), float64
        Hit point, world frame, mm; NaN off the mask.
    depth : ndarray of shape (H, W), float32
        Camera-frame z of the hit, mm; inf off the mask.
    uv : ndarray of shape (H, W, 2), float32
        Surface coordinates (see the surface classes); NaN where undefined.
    face_index : ndarray of shape (H, W), int32
        Mesh triangle hit, -1 elsewhere.
    surface_index : ndarray of shape (H, W), int32
        Index into ``scene.objects``, -1 off the mask.
    diffuse, specular : ndarray of shape (H, W, 3), float32, or None
        With ``render(..., components=True)``: the body (depolarised) reflection and the rest
        (interface reflection, mirrors and what they show), after the analyser; zero off the
        mask, so ``radiance = diffuse + specular`` there and the background elsewhere.
    """

    radiance: np.ndarray
    mask: np.ndarray
    normal: np.ndarray
    position: np.ndarray
    depth: np.ndarray
    uv: np.ndarray
    face_index: np.ndarray
    surface_index: np.ndarray
    diffuse: np.ndarray | None = None
    specular: np.ndarray | None = None


class PrimaryHits:
    """The camera rays and their first hits, kept by one :func:`render` for the next ones of the
    same geometry through the same camera (``render(..., primary=...)``).

    What a frame's camera rays hit depends on the surfaces and the camera only; a capture renders
    one pose under many lights and analyser angles, so later frames start from the kept hits and
    trace only what depends on the lights (shading, shadow and mirror rays): the same arithmetic,
    the same bytes. The caller owns the promise that the surfaces and the camera are unchanged;
    the image size and the chunk rows are checked. The kept arrays are read-only.
    """

    def __init__(self) -> None:
        self._layout: tuple[int, int, int] | None = None  # (width, height, rows per chunk)
        self._chunks: dict[int, tuple[np.ndarray, np.ndarray, Hits]] = {}

    def _bind(self, width: int, height: int, rows: int) -> None:
        layout = (width, height, rows)
        if self._layout is None:
            self._layout = layout
        elif self._layout != layout:
            raise ValueError(f"primary hits were kept for a {self._layout[0]} x {self._layout[1]} "
                             f"image in chunks of {self._layout[2]} rows, not {width} x {height} "
                             f"in chunks of {rows}: use a new PrimaryHits for another camera")

    def _get(self, r0: int, compute):
        """The chunk starting at row ``r0``: kept, or ``compute()`` -> (o, d, hits) kept."""
        kept = self._chunks.get(r0)
        if kept is None:
            kept = compute()
            for a in (kept[1], *vars(kept[2]).values()):
                a.flags.writeable = False
            self._chunks[r0] = kept  # chunks are disjoint: threads never share a key
        return kept


@dataclass(frozen=True)
class _Options:
    shadows: bool
    analyser: float | None
    env_samples: int
    env_sampling: str
    max_bounces: int
    rng: np.random.Generator
    components: bool = False


# ----------------------------------------------------------------------------------------------
# public entry points
# ----------------------------------------------------------------------------------------------
def render(scene: Scene, camera: CameraModel, *, shadows: bool = True,
           polarizer: float | None = None, env_samples: int = 64,
           env_sampling: str = "mis", max_bounces: int = 2, rng=0,
           background=None, chunk: int = DEFAULT_CHUNK,
           threads: int | None = None, components: bool = False,
           primary: PrimaryHits | None = None) -> RenderResult:
    """Render ``scene`` as seen by ``camera``.

    Parameters
    ----------
    scene : Scene
    camera : CameraModel
        Intrinsics, distortion and world -> camera pose.
    shadows : bool
        Cast shadow rays to point/directional lights and environment samples.
    polarizer : float or None
        Analyser angle on the lens, degrees (see module docstring); None: no analyser.
    env_samples : int
        Monte-Carlo samples per pixel for the environment map (ignored without one).
    env_sampling : {'mis', 'importance', 'uniform'}
        Environment sampling: 'mis' (half the samples by luminance x solid angle, half
        cosine-weighted about the normal — an odd count gives the map one more — combined by
        the balance heuristic with each strategy's sample count; robust for bright, small sources
        and broad skies alike), 'importance' (luminance x solid angle only) or 'uniform' over
        the sphere. All are unbiased estimates of the piecewise-constant map's reflection.
    max_bounces : int
        How many mirror reflections a ray may follow (0: mirrors see nothing).
    rng : int or numpy.random.Generator
        Seed or generator of the Monte-Carlo sampling. Each chunk of rows draws from its own
        child generator (``Generator.spawn``), so a frame is reproducible for a given seed and
        ``chunk`` whatever the number of threads.
    background : None or float or (3,)
        Radiance of pixels that hit nothing; None: the environment map seen through the
        (analyser), black without one.
    chunk : int
        Camera rays processed together (memory bound: ~1 kB per ray in flight per thread).
    threads : int or None
        Chunks rendered concurrently (numpy releases the GIL in its array loops); None: the
        CPUs available to this process, at most 4.
    components : bool
        Also return ``diffuse`` and ``specular`` radiance buffers (ground truth for
        diffuse/specular separation); costs a second BRDF evaluation per light.
    primary : PrimaryHits, optional
        The camera rays' first hits kept from an earlier render of the same surfaces through the
        same camera (filled by the first render given it); see :class:`PrimaryHits`.

    Returns
    -------
    RenderResult

    Examples
    --------
    >>> from reconstruct.brdf import Lambertian
    >>> from reconstruct.raycast import Sphere
    >>> sc = Scene()
    >>> _ = sc.add(Sphere(40.0, center=(0, 0, 50)), Lambertian(0.5), "ball")
    >>> sc.add_light(PointLight((100.0, -200.0, 150.0), intensity=1e5))
    >>> cam = CameraModel.look_at((0, -300, 50), (0, 0, 50), width=64, height=48)
    >>> res = render(sc, cam)
    >>> res.radiance.shape, bool(res.mask[24, 32])
    ((48, 64, 3), True)
    """
    _check_scene(scene)
    if not isinstance(camera, CameraModel):
        raise TypeError(f"camera must be a CameraModel, got {type(camera).__name__}")
    if int(chunk) < 1:
        raise ValueError(f"chunk must be >= 1, got {chunk!r}")
    if threads is None:
        threads = min(4, len(os.sched_getaffinity(0)))
    if int(threads) < 1:
        raise ValueError(f"threads must be >= 1, got {threads!r}")
    H, W = camera.height, camera.width
    n = H * W
    rad = np.zeros((n, 3), np.float32)
    mask = np.zeros(n, bool)
    normal = np.zeros((n, 3), np.float32)
    position = np.full((n, 3), np.nan)
    uv = np.full((n, 2), np.nan, np.float32)
    face = np.full(n, -1, np.int32)
    surf = np.full(n, -1, np.int32)
    opts = replace(_options(shadows, polarizer, env_samples, env_sampling, max_bounces, rng),
                   components=bool(components))
    bg = None if background is None else _rgb3("background", background)
    diffuse = np.zeros((n, 3), np.float32) if components else None
    specular = np.zeros((n, 3), np.float32) if components else None
    rows = max(1, int(chunk) // W)
    starts = list(range(0, H, rows))
    surfaces = scene.surfaces
    if primary is not None:
        primary._bind(W, H, rows)

    def camera_hits(r0, r1):
        o, d = camera.row_rays(r0, r1)
        return o, d, _first_hits(surfaces, o, d) if surfaces else _no_hits(len(d))

    def run(r0, gen):
        r1 = min(H, r0 + rows)
        sl = slice(r0 * W, r1 * W)
        o, d, first = camera_hits(r0, r1) if primary is None else primary._get(
            r0, lambda: camera_hits(r0, r1))
        L, Ld, hits = _trace(scene, o, d, replace(opts, rng=gen), 0, bg, first)
        rad[sl] = L  # chunks write disjoint slices: safe from threads
        if components:
            diffuse[sl] = Ld
            specular[sl] = np.where(hits.mask[:, None], L - Ld, 0.0)
        mask[sl] = hits.mask
        normal[sl] = hits.normal
        position[sl] = hits.position
        uv[sl] = hits.uv
        face[sl] = hits.face_index
        surf[sl] = hits.surface_index

    gens = opts.rng.spawn(len(starts))
    if int(threads) == 1 or len(starts) == 1:
        for r0, gen in zip(starts, gens):
            run(r0, gen)
    else:
        with ThreadPoolExecutor(max_workers=int(threads)) as pool:
            for f in [pool.submit(run, r0, gen) for r0, gen in zip(starts, gens)]:
                f.result()
    depth = np.where(mask, position @ camera.R[2] + camera.t[2], np.inf).astype(np.float32)
    return RenderResult(radiance=rad.reshape(H, W, 3), mask=mask.reshape(H, W),
                        normal=normal.reshape(H, W, 3), position=position.reshape(H, W, 3),
                        depth=depth.reshape(H, W), uv=uv.reshape(H, W, 2),
                        face_index=face.reshape(H, W), surface_index=surf.reshape(H, W),
                        diffuse=None if diffuse is None else diffuse.reshape(H, W, 3),
                        specular=None if specular is None else specular.reshape(H, W, 3))


def render_rays(scene: Scene, origins, dirs, *, shadows: bool = True,
                polarizer: float | None = None, env_samples: int = 64,
                env_sampling: str = "mis", max_bounces: int = 2, rng=0,
                background=None) -> tuple[np.ndarray, Hits]:
    """Radiance seen along world rays ``origins + t dirs`` (origins (N, 3) mm, dirs (N, 3)):
    what a sensor at ``origins`` looking along ``dirs`` measures (any camera model, lumitexel
    validation, probes).

    Options as :func:`render`. Returns radiance (N, 3) float32 and the first :class:`Hits`.
    """
    _check_scene(scene)
    o, d = _check_rays(origins, dirs)
    norm = np.linalg.norm(d, axis=1, keepdims=True)
    if np.any(norm == 0):
        raise ValueError("dirs must be non-zero vectors")
    d = d / norm
    opts = _options(shadows, polarizer, env_samples, env_sampling, max_bounces, rng)
    bg = None if background is None else _rgb3("background", background)
    L, _, hits = _trace(scene, np.ascontiguousarray(o), d, opts, 0, bg)
    return L, hits


def _check_scene(scene) -> None:
    if not isinstance(scene, Scene):
        raise TypeError(f"scene must be a render.Scene, got {type(scene).__name__}")
    for i, light in enumerate(scene.lights):
        if not isinstance(light, (PointLight, DirectionalLight)):
            raise TypeError(f"scene.lights[{i}] must be a PointLight or DirectionalLight, got "
                            f"{type(light).__name__}")
    for i, obj in enumerate(scene.objects):
        if not isinstance(obj, SceneObject):
            raise TypeError(f"scene.objects[{i}] must be a SceneObject, got "
                            f"{type(obj).__name__}")
    if scene.environment is not None and not isinstance(scene.environment, EnvironmentMap):
        raise TypeError(f"scene.environment must be an EnvironmentMap or None, got "
                        f"{type(scene.environment).__name__}")


def _options(shadows, polarizer, env_samples, env_sampling, max_bounces, rng) -> _Options:
    if env_sampling not in ("mis", "importance", "uniform"):
        raise ValueError(f"env_sampling must be 'mis', 'importance' or 'uniform', got "
                         f"{env_sampling!r}")
    if int(env_samples) < 0:
        raise ValueError(f"env_samples must be >= 0, got {env_samples!r}")
    if int(max_bounces) < 0:
        raise ValueError(f"max_bounces must be >= 0, got {max_bounces!r}")
    if isinstance(rng, (bool, float)) or not isinstance(rng, (int, np.integer,
                                                              np.random.Generator)):
        raise TypeError(f"rng must be an int seed or a numpy.random.Generator, got {rng!r}")
    return _Options(bool(shadows), _angle("polarizer", polarizer), int(env_samples),
                    env_sampling, int(max_bounces), np.random.default_rng(rng))


# ----------------------------------------------------------------------------------------------
# transport
# ----------------------------------------------------------------------------------------------
def _weights(opts: _Options, light_polarizer):
    """(diffuse, specular) transmission of the analyser for light of the given polarization."""
    if opts.analyser is None:
        return 1.0, 1.0
    if light_polarizer is None:
        return 0.5, 0.5
    return 0.5, float(np.cos(np.radians(light_polarizer - opts.analyser)) ** 2)


def _env_weight(opts: _Options) -> float:
    return 1.0 if opts.analyser is None else 0.5


def _trace(scene: Scene, o, d, opts: _Options, depth: int, background, hits: Hits | None = None):
    """Radiance along rays (unit ``d``), its diffuse part (None unless ``opts.components``)
    and the rays' first hits (``hits``: already found, else traced here)."""
    surfaces = scene.surfaces
    n = len(d)
    L = np.zeros((n, 3))
    Ld = np.zeros((n, 3)) if opts.components else None
    if hits is None:
        hits = _first_hits(surfaces, o, d) if surfaces else _no_hits(n)
    miss = ~hits.mask
    if np.any(miss):
        if background is not None and depth == 0:
            L[miss] = background
        elif scene.environment is not None:
            L[miss] = _env_weight(opts) * scene.environment.lookup(d[miss])
        if depth > 0:  # light spheres are seen only through mirrors
            L[miss] += _light_spheres(scene, o[miss], d[miss], np.inf, opts)
    idx = np.flatnonzero(hits.mask)
    if len(idx):
        L[idx], dif = _shade(scene, hits, idx, d[idx], opts, depth)
        if Ld is not None:
            Ld[idx] = dif
    if depth > 0 and len(idx):
        L[idx] += _light_spheres(scene, o[idx], d[idx], hits.t[idx], opts)
    return L.astype(np.float32), Ld, hits


def _no_hits(n) -> Hits:
    return Hits(t=np.full(n, np.inf), position=np.full((n, 3), np.nan), normal=np.zeros((n, 3)),
                geometric_normal=np.zeros((n, 3)), uv=np.full((n, 2), np.nan),
                face_index=np.full(n, -1, np.int64), surface_index=np.full(n, -1, np.int64),
                mask=np.zeros(n, bool))


def _light_spheres(scene, o, d, t_limit, opts):
    """Radiance of spherical point lights (radius > 0) hit by rays before ``t_limit``."""
    L = np.zeros((len(d), 3))
    best = np.broadcast_to(np.asarray(t_limit, float), (len(d),)).copy()
    for light in scene.lights:
        if not isinstance(light, PointLight) or light.radius <= 0:
            continue
        oc = o - light.position
        b = np.einsum("ij,ij->i", d, oc)
        disc = b * b - (np.einsum("ij,ij->i", oc, oc) - light.radius ** 2)
        t = -b - np.sqrt(np.maximum(disc, 0.0))
        hit = (disc >= 0) & (t > 0) & (t < best)
        if np.any(hit):
            best[hit] = t[hit]
            # a mirror keeps the light's polarization: the specular weight applies
            L[hit] = _weights(opts, light.polarizer)[1] * light.intensity / (np.pi * light.radius
                                                                             ** 2)
    return L


def _shade(scene: Scene, hits: Hits, idx, d, opts: _Options, depth: int):
    """Radiance leaving hit points ``idx`` towards ``-d`` (unit, (M, 3)) and its diffuse part
    (None unless ``opts.components``)."""
    M = len(idx)
    p = hits.position[idx]
    ng = hits.geometric_normal[idx]
    ns = hits.normal[idx]
    owner = hits.surface_index[idx]
    wo = -d
    # two-sided surfaces: face the viewer
    back = np.einsum("ij,ij->i", ng, wo) < 0
    if np.any(back):
        ng[back] *= -1
        ns[back] *= -1

    # per-point materials: list of (local indices, BRDF-or-Mirror)
    groups = []
    uv, face = hits.uv[idx], hits.face_index[idx]
    for k in np.unique(owner):
        sel = np.flatnonzero(owner == k) if len(scene.objects) > 1 else np.arange(M)
        groups.extend(_resolve(scene.objects[k], sel, p[sel], uv[sel], face[sel]))

    out = np.zeros((M, 3))
    out_d = np.zeros((M, 3)) if opts.components else None
    brdf_groups = [(s, m) for s, m in groups if isinstance(m, BRDF)]
    scale = scene_scale(scene.surfaces, p)
    if brdf_groups:
        frames = tangent_frames(ns)
        wo_l = to_local(wo, frames)
        for light in scene.lights:
            wi, g = _light_geometry(scene, light, p, ng, scale, opts.shadows)
            wi_l = to_local(wi, frames)
            g *= np.clip(wi_l[:, 2], 0.0, None)  # cos(theta_i) / r^2 (or 1), zero in shadow
            gain = light.intensity if isinstance(light, PointLight) else light.irradiance
            w = _weights(opts, light.polarizer)
            for sel, brdf in brdf_groups:
                f, fd = _split_eval(brdf, wi_l[sel], wo_l[sel], w, opts.components)
                scale_sel = g[sel, None] * gain
                out[sel] += f * scale_sel
                if fd is not None:
                    out_d[sel] += fd * scale_sel
        if scene.environment is not None and opts.env_samples > 0:
            for sel, brdf in brdf_groups:
                Le, Led = _env_lighting(scene, brdf, p[sel], ng[sel], frames[sel], wo_l[sel],
                                        opts, scale)
                out[sel] += Le
                if Led is not None:
                    out_d[sel] += Led
    for sel, mirror in groups:
        if not isinstance(mirror, Mirror) or depth >= opts.max_bounces:
            continue
        r = reflect(d[sel], ns[sel])
        Lr = _trace(scene, offset_origins(p[sel], ng[sel], r, scale), r, opts, depth + 1,
                    None)[0]
        out[sel] += np.asarray(mirror.reflectance, float) * Lr  # all specular
    return out, out_d


def _resolve(obj: SceneObject, sel, p, uv, face):
    """Split the points ``sel`` of one object by material -> [(indices, BRDF or Mirror)]."""
    mat = obj.material
    if isinstance(mat, MaterialMap):
        ids = mat.resolve_ids(p, uv, face)
        out = []
        for m in np.unique(ids):
            sub = np.flatnonzero(ids == m)
            out.extend((sel[s], b) for s, b in
                       _resolve(SceneObject(obj.surface, mat.materials[m], obj.name), sub,
                                p[sub], uv[sub], face[sub]))
        return out
    if isinstance(mat, (BRDF, Mirror)):
        return [(sel, mat)]
    brdf = mat(p, uv, face)
    if not isinstance(brdf, (BRDF, Mirror)):
        raise TypeError(f"material callable of {obj.name or 'object'} returned "
                        f"{type(brdf).__name__}, expected a BRDF with (N,)-shaped parameters")
    return [(sel, brdf)]


def _split_eval(brdf: BRDF, wi_l, wo_l, weights, want_diffuse: bool):
    """f_r weighted by the analyser, w_d * diffuse part + w_s * specular part, and the weighted
    diffuse part alone (None unless ``want_diffuse``)."""
    wd, ws = weights
    if wd == ws and not want_diffuse:
        return wd * brdf.evaluate(wi_l, wo_l), None
    fd = wd * brdf.diffuse_part().evaluate(wi_l, wo_l)
    return fd + ws * brdf.specular_part().evaluate(wi_l, wo_l), fd if want_diffuse else None


def _light_geometry(scene, light, p, ng, scale, shadows):
    """Unit directions (M, 3) from points ``p`` to the light and the geometric factor (M,):
    1 / r^2 (mm^-2) for a point light, 1 for a directional one, zero where shadowed."""
    if isinstance(light, PointLight):
        v = light.position - p
        dist = np.sqrt(np.einsum("ij,ij->i", v, v))
        wi = v / dist[:, None]
        g = 1.0 / dist ** 2
    else:
        dist = np.full(len(p), np.inf)
        wi = np.broadcast_to(light.direction, p.shape)
        g = np.ones(len(p))
    if shadows:
        front = np.einsum("ij,ij->i", wi, ng) > 0
        g[~front] = 0.0  # the light is behind the face itself (even if the shading normal is not)
        o = p + (OFFSET_EPS * scale) * ng  # the light is on the normal's side
        # back faces get a zero-length ray (their g is already 0, so its answer does not matter):
        # cheaper than gathering the front-facing rays and scattering the result back
        t_max = np.where(front, dist - 2 * OFFSET_EPS * scale, 0.0)
        g[_occluded(scene.surfaces, o, wi, t_max)] = 0.0
    return wi, g


def _env_lighting(scene, brdf: BRDF, p, ng, frames, wo_l, opts: _Options, scale):
    """Monte-Carlo estimate of the environment's reflected radiance at points (K, 3) and its
    diffuse part (None unless ``opts.components``): one direction per point per pass,
    ``env_samples`` passes (memory O(K); the BRDF's per-point parameters stay aligned with the
    points). The environment is unpolarized: the analyser passes half of both parts."""
    env = scene.environment
    K = len(p)
    S = opts.env_samples
    acc = np.zeros((K, 3))
    acc_d = np.zeros((K, 3)) if opts.components else None
    diffuse = brdf.diffuse_part() if opts.components else None
    n_cos = S // 2  # 'mis': odd passes are cosine-weighted, so an odd S has one more map sample
    n_env = S - n_cos
    for j in range(S):
        if opts.env_sampling == "mis" and j % 2 == 1:
            wi_l = _cosine_hemisphere(K, opts.rng)
            wi = np.einsum("nji,nj->ni", frames, wi_l)
        else:
            wi = env.sample(K, opts.rng, method="uniform" if opts.env_sampling == "uniform"
                            else "importance")[0]
            wi_l = to_local(wi, frames)
        cos_i = np.clip(wi_l[:, 2], 0.0, None)
        L_env, pdf = env.lookup_pdf(wi)
        if opts.env_sampling == "mis":  # balance heuristic, each strategy by its sample count
            pdf = (n_env * pdf + n_cos * cos_i / np.pi) / S
        elif opts.env_sampling == "uniform":
            pdf = np.full(K, 1 / (4 * np.pi))
        with np.errstate(divide="ignore", invalid="ignore"):
            weight = np.where(cos_i > 0, cos_i / pdf, 0.0)
        incident = L_env * weight[:, None]
        contrib = brdf.evaluate(wi_l, wo_l) * incident
        if opts.shadows:
            live = np.flatnonzero(np.any(contrib > 0, axis=1))
            o = offset_origins(p[live], ng[live], wi[live], scale)
            blocked = live[_occluded(scene.surfaces, o, wi[live], np.full(len(live), np.inf))]
            contrib[blocked] = 0.0
            incident[blocked] = 0.0
        acc += contrib
        if acc_d is not None:
            acc_d += diffuse.evaluate(wi_l, wo_l) * incident
    w = _env_weight(opts) / S
    return w * acc, None if acc_d is None else w * acc_d


def _cosine_hemisphere(n: int, rng: np.random.Generator) -> np.ndarray:
    """Cosine-weighted local directions (n, 3) about +z (pdf cos(theta) / pi)."""
    r = np.sqrt(rng.random(n))
    phi = 2 * np.pi * rng.random(n)
    return np.stack([r * np.cos(phi), r * np.sin(phi), np.sqrt(np.maximum(0.0, 1 - r * r))],
                    axis=1)
