"""Calibration targets of the simulated rig: printed boards, spheres, a gray card, environments.

Every target knows its own geometry in millimetres and builds the ray-castable surfaces
(``reconstruct.raycast``) and materials (``reconstruct.brdf``) that the scene hands to the
renderer. A material is either a BRDF or a callable ``material(position (N, 3), uv (N, 2),
face_index (N,)) -> BRDF`` with per-sample parameters (an SVBRDF), the renderer's convention.

Board frame (the one OpenCV's calibration uses for object points): x to the right along the
printed rows, y down along the columns, z = x cross y pointing *into* the board, so the printed
face looks towards -z; millimetres. ``pose`` arguments are 4x4 board -> world matrices (world =
turntable frame, +z up).
"""
from __future__ import annotations

import functools
import warnings
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from reconstruct.brdf import BRDF, CookTorrance, Lambertian
from reconstruct.envmap import EnvironmentMap
from reconstruct.raycast import Plane, Sphere
from reconstruct.render import Mirror, SceneObject

from .objects import shared_data_dir

#: Reflectance of printed paper: laser-toner black and white office paper (broadband).
PAPER_BLACK = 0.04
PAPER_WHITE = 0.85
#: Specular reflectance of polished chrome and of bearing steel at normal incidence (visible band).
CHROME_REFLECTANCE = 0.65
STEEL_REFLECTANCE = 0.55
#: Kodak-style gray card.
GRAY_CARD_ALBEDO = 0.18
PROBES = ("grace", "uffizi", "ennis")


def check_pose(pose, name: str = "pose") -> np.ndarray:
    """A 4x4 rigid object -> world matrix (rotation + translation in mm), validated."""
    T = np.asarray(pose, dtype=np.float64)
    if T.shape != (4, 4) or not np.allclose(T[3], [0, 0, 0, 1]):
        raise ValueError(f"{name} must be a 4x4 rigid transform (last row 0 0 0 1), got shape {T.shape}")
    R = T[:3, :3]
    if not np.allclose(R @ R.T, np.eye(3), atol=1e-6) or np.linalg.det(R) < 0:
        raise ValueError(f"{name} rotation must be a proper rotation matrix (orthonormal, det +1)")
    return T


def pose_facing(center_mm, toward_mm, *, up=(0.0, 0.0, 1.0)) -> np.ndarray:
    """A 4x4 pose at ``center_mm`` (world, mm) with board axes: -z (the printed face) looking
    towards ``toward_mm`` (e.g. the camera centre), y pointing as much down (against world
    ``up``) as possible, x to the right as seen from ``toward_mm``. Feed it to
    :meth:`PrintedBoard.centered_pose` to place a sheet's centre there."""
    c = np.asarray(center_mm, float)
    face = np.asarray(toward_mm, float) - c
    if np.linalg.norm(face) == 0:
        raise ValueError("toward_mm must differ from center_mm")
    z = -face / np.linalg.norm(face)                  # board z points away from the viewer
    x = np.cross(z, np.asarray(up, float))            # right as seen from the viewer
    if np.linalg.norm(x) < 1e-9:
        raise ValueError("up is parallel to the board normal; give another 'up'")
    x /= np.linalg.norm(x)
    y = np.cross(z, x)                                # down
    T = np.eye(4)
    T[:3, 0], T[:3, 1], T[:3, 2], T[:3, 3] = x, y, z, c
    return T


# ----------------------------------------------------------------------------------------------
# printed boards
# ----------------------------------------------------------------------------------------------
class PrintedBoard:
    """A flat printed target: an albedo texture (uint8, 0 = black toner, 255 = white paper) on a
    Lambertian plane. Subclasses define the texture and the object points."""

    px_per_mm: float
    albedo_black: float
    albedo_white: float

    # -- geometry in the board frame --------------------------------------------------------------
    @property
    def extent_mm(self) -> tuple[float, float, float, float]:
        """(x_min, y_min, x_max, y_max) of the printed sheet in the board frame, mm."""
        raise NotImplementedError

    def object_points(self) -> np.ndarray:
        """Corner positions in the board frame, (N, 3) mm, z = 0, in the detector's order."""
        raise NotImplementedError

    def texture(self) -> np.ndarray:
        """The printed image, (H, W) uint8, row 0 at ``y_min``, ``px_per_mm`` pixels per mm."""
        raise NotImplementedError

    @property
    def size_mm(self) -> tuple[float, float]:
        x0, y0, x1, y1 = self.extent_mm
        return x1 - x0, y1 - y0

    @property
    def center_mm(self) -> np.ndarray:
        """Centre of the sheet in the board frame, (3,) mm."""
        x0, y0, x1, y1 = self.extent_mm
        return np.array([(x0 + x1) / 2, (y0 + y1) / 2, 0.0])

    def centered_pose(self, pose_of_center) -> np.ndarray:
        """Board -> world pose for a sheet whose *centre* has the 4x4 pose ``pose_of_center``."""
        T = check_pose(pose_of_center).copy()
        T[:3, 3] = T[:3, 3] - T[:3, :3] @ self.center_mm
        return T

    def corners_world(self, pose) -> np.ndarray:
        """:meth:`object_points` in the world frame for a board -> world ``pose``, (N, 3) mm."""
        T = check_pose(pose)
        return self.object_points() @ T[:3, :3].T + T[:3, 3]

    # -- appearance -------------------------------------------------------------------------------
    def albedo_at(self, board_xy_mm: np.ndarray) -> np.ndarray:
        """Albedo of the sheet at board-frame points (N, 2) mm -> (N,), bilinear in the texture;
        paper white outside the texture."""
        xy = np.asarray(board_xy_mm, dtype=np.float64).reshape(-1, 2)
        x0, y0, _, _ = self.extent_mm
        tex = _padded_texture(self)  # one texel of white paper around the print
        # texel (i, j) covers [j, j + 1) / px_per_mm, so its centre sits at j + 1/2 (+1: padding)
        px = np.clip((xy[:, 0] - x0) * self.px_per_mm + 0.5, 0.0, tex.shape[1] - 1.001)
        py = np.clip((xy[:, 1] - y0) * self.px_per_mm + 0.5, 0.0, tex.shape[0] - 1.001)
        j, i = px.astype(np.int64), py.astype(np.int64)
        fx, fy = px - j, py - i
        t = (tex[i, j] * (1 - fx) + tex[i, j + 1] * fx) * (1 - fy) + \
            (tex[i + 1, j] * (1 - fx) + tex[i + 1, j + 1] * fx) * fy
        return self.albedo_black + (self.albedo_white - self.albedo_black) * (t / 255.0)

    def material(self):
        """SVBRDF: Lambertian with the printed albedo, looked up through the plane's uv."""
        w, h = self.size_mm
        x0, y0, _, _ = self.extent_mm

        def printed(position, uv, face_index) -> BRDF:
            uv = np.asarray(uv, dtype=np.float64).reshape(-1, 2)
            # plane frame (x_b, -y_b, -z_b): u runs along board x, v against board y
            xy = np.stack([x0 + uv[:, 0] * w, y0 + (1.0 - uv[:, 1]) * h], axis=1)
            return Lambertian(np.repeat(self.albedo_at(xy)[:, None], 3, axis=1))

        return printed

    def surface(self, pose) -> Plane:
        """The sheet as a finite :class:`reconstruct.raycast.Plane` (its +z = the printed face's
        outward normal = -z of the board) for a board -> world ``pose``."""
        T = check_pose(pose)
        board_from_plane = np.diag([1.0, -1.0, -1.0, 1.0])
        board_from_plane[:3, 3] = self.center_mm
        return Plane(self.size_mm, T @ board_from_plane)

    def scene_object(self, pose, name: str | None = None) -> SceneObject:
        """The sheet with its printed material, ready for ``reconstruct.render.Scene``."""
        return SceneObject(self.surface(pose), self.material(), name or type(self).__name__.lower())


@dataclass(frozen=True, eq=False)
class Checkerboard(PrintedBoard):
    """A printed chessboard with ``inner_corners = (columns, rows)`` inner corners (OpenCV's
    ``patternSize``), squares of ``square_mm``, a white margin of ``margin_mm``.

    Board frame origin: the first inner corner (top-left as printed), so ``object_points`` are
    ``(j * square, i * square, 0)`` in row-major order (j fastest) — what
    ``cv2.calibrateCamera`` users write. The top-left square is black.
    """

    inner_corners: tuple[int, int] = (9, 6)
    square_mm: float = 20.0
    margin_mm: float = 15.0
    px_per_mm: float = 8.0
    albedo_black: float = PAPER_BLACK
    albedo_white: float = PAPER_WHITE

    def __post_init__(self) -> None:
        cols, rows = (int(v) for v in self.inner_corners)
        if cols < 2 or rows < 2:
            raise ValueError(f"inner_corners must be (columns, rows) >= (2, 2), got {self.inner_corners!r}")
        for name in ("square_mm", "px_per_mm"):
            if not getattr(self, name) > 0:
                raise ValueError(f"{name} must be > 0, got {getattr(self, name)!r}")
        if self.margin_mm < 0:
            raise ValueError(f"margin_mm must be >= 0, got {self.margin_mm!r}")
        _check_albedos(self)

    @property
    def extent_mm(self):
        cols, rows = self.inner_corners
        s, m = self.square_mm, self.margin_mm
        return -s - m, -s - m, cols * s + m, rows * s + m

    def object_points(self) -> np.ndarray:
        cols, rows = self.inner_corners
        j, i = np.meshgrid(np.arange(cols), np.arange(rows))
        return np.stack([j.ravel(), i.ravel(), np.zeros(j.size)], axis=1) * self.square_mm

    def texture(self) -> np.ndarray:
        return _checker_texture(self.inner_corners, self.square_mm, self.margin_mm, self.px_per_mm)


@functools.lru_cache(maxsize=8)
def _checker_texture(inner, square, margin, ppmm) -> np.ndarray:
    cols, rows = inner
    w = int(round(((cols + 1) * square + 2 * margin) * ppmm))
    h = int(round(((rows + 1) * square + 2 * margin) * ppmm))
    # board coordinates (relative to the outer corner of the squares) of the texel centres
    x = (np.arange(w) + 0.5) / ppmm - margin
    y = (np.arange(h) + 0.5) / ppmm - margin
    ix = np.floor(x / square)[None, :]
    iy = np.floor(y / square)[:, None]
    inside = (ix >= 0) & (ix <= cols) & (iy >= 0) & (iy <= rows)
    black = inside & ((ix + iy) % 2 == 0)
    tex = np.where(black, 0, 255).astype(np.uint8)
    tex.flags.writeable = False
    return tex


@dataclass(frozen=True, eq=False)
class CharucoTarget(PrintedBoard):
    """A ChArUco board (``cv2.aruco.CharucoBoard``): ``squares = (columns, rows)`` chessboard
    squares of ``square_mm`` with ArUco markers of ``marker_mm`` from ``dictionary`` in the white
    squares, a white margin of ``margin_mm``.

    Board frame: OpenCV's — origin at the top-left outer corner of the square grid; the
    ``object_points`` are ``board.getChessboardCorners()`` (ids 0..N-1 in that order).
    """

    squares: tuple[int, int] = (7, 5)
    square_mm: float = 30.0
    marker_mm: float = 22.0
    dictionary: str = "DICT_5X5_100"
    margin_mm: float = 10.0
    px_per_mm: float = 8.0
    albedo_black: float = PAPER_BLACK
    albedo_white: float = PAPER_WHITE

    def __post_init__(self) -> None:
        if not hasattr(cv2.aruco, self.dictionary):
            raise ValueError(f"dictionary {self.dictionary!r} is not a cv2.aruco predefined dictionary")
        if not 0 < self.marker_mm < self.square_mm:
            raise ValueError(f"marker_mm must be in (0, square_mm={self.square_mm}), got {self.marker_mm!r}")
        if min(int(v) for v in self.squares) < 2:
            raise ValueError(f"squares must be (columns, rows) >= (2, 2), got {self.squares!r}")
        if self.margin_mm < 0 or not self.px_per_mm > 0:
            raise ValueError("margin_mm must be >= 0 and px_per_mm > 0")
        _check_albedos(self)

    def board(self) -> "cv2.aruco.CharucoBoard":
        """The OpenCV board (lengths in mm), as a detector would build it."""
        d = cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, self.dictionary))
        return cv2.aruco.CharucoBoard(tuple(int(v) for v in self.squares), float(self.square_mm),
                                      float(self.marker_mm), d)

    @property
    def extent_mm(self):
        cols, rows = self.squares
        m = self.margin_mm
        return -m, -m, cols * self.square_mm + m, rows * self.square_mm + m

    def object_points(self) -> np.ndarray:
        return np.asarray(self.board().getChessboardCorners(), dtype=np.float64).reshape(-1, 3)

    def texture(self) -> np.ndarray:
        return _charuco_texture(self)


@functools.lru_cache(maxsize=8)
def _charuco_texture(target: CharucoTarget) -> np.ndarray:
    cols, rows = target.squares
    ppmm = target.px_per_mm
    w = int(round((cols * target.square_mm + 2 * target.margin_mm) * ppmm))
    h = int(round((rows * target.square_mm + 2 * target.margin_mm) * ppmm))
    tex = target.board().generateImage((w, h), marginSize=int(round(target.margin_mm * ppmm)),
                                       borderBits=1)
    tex.flags.writeable = False
    return tex


@functools.lru_cache(maxsize=8)
def _padded_texture(board: PrintedBoard) -> np.ndarray:
    return np.pad(board.texture().astype(np.float32), 1, constant_values=255.0)


def _check_albedos(board) -> None:
    if not 0 <= board.albedo_black < board.albedo_white <= 1:
        raise ValueError(f"albedos must satisfy 0 <= albedo_black < albedo_white <= 1, got "
                         f"{board.albedo_black!r}, {board.albedo_white!r}")


# ----------------------------------------------------------------------------------------------
# gray card
# ----------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class GrayCard:
    """An 18 % gray card (Lambertian), ``size_mm = (width, height)``; board frame as the printed
    boards (origin at the card's centre here, printed face towards -z)."""

    size_mm: tuple[float, float] = (100.0, 125.0)
    albedo: float = GRAY_CARD_ALBEDO

    def __post_init__(self) -> None:
        if len(self.size_mm) != 2 or min(self.size_mm) <= 0:
            raise ValueError(f"size_mm must be (width, height) > 0, got {self.size_mm!r}")
        if not 0 < self.albedo <= 1:
            raise ValueError(f"albedo must be in (0, 1], got {self.albedo!r}")

    def surface(self, pose) -> Plane:
        return Plane(self.size_mm, check_pose(pose) @ np.diag([1.0, -1.0, -1.0, 1.0]))

    def scene_object(self, pose, name: str = "gray_card") -> SceneObject:
        return SceneObject(self.surface(pose), Lambertian(self.albedo), name)


# ----------------------------------------------------------------------------------------------
# spheres
# ----------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class CalibrationSphere:
    """A sphere of known ``radius_mm``: ``kind`` ``"chrome"`` (mirror, light probes and light
    localisation), ``"steel"`` (polished bearing ball) or ``"matte"`` (Lambertian, ``albedo``).

    The mirror kinds are perfect reflectors (``reconstruct.render.Mirror``) of :attr:`reflectance`;
    the point light needs a radius > 0 to show a highlight in them."""

    radius_mm: float = 25.4
    kind: str = "chrome"
    albedo: float = 0.8

    def __post_init__(self) -> None:
        if not self.radius_mm > 0:
            raise ValueError(f"radius_mm must be > 0, got {self.radius_mm!r}")
        if self.kind not in ("chrome", "steel", "matte"):
            raise ValueError(f"kind must be 'chrome', 'steel' or 'matte', got {self.kind!r}")
        if not 0 < self.albedo <= 1:
            raise ValueError(f"albedo must be in (0, 1], got {self.albedo!r}")

    @property
    def reflectance(self) -> float:
        return {"chrome": CHROME_REFLECTANCE, "steel": STEEL_REFLECTANCE}.get(self.kind, 0.0)

    def surface(self, center_mm) -> Sphere:
        c = np.asarray(center_mm, dtype=np.float64)
        if c.shape != (3,):
            raise ValueError(f"center_mm must be a 3-vector (world, mm), got shape {c.shape}")
        return Sphere(self.radius_mm, c)

    def material(self):
        return Lambertian(self.albedo) if self.kind == "matte" else Mirror(self.reflectance)

    def scene_object(self, center_mm, name: str | None = None) -> SceneObject:
        return SceneObject(self.surface(center_mm), self.material(), name or f"{self.kind}_sphere")


#: the sample sphere's material: a glossy dielectric (red-brown plastic) with a visible lobe,
#: GGX roughness 0.12 over a coloured body (Cook-Torrance, Schlick f0 = 0.04)
SAMPLE_MATERIAL = CookTorrance(kd=(0.30, 0.12, 0.06), f0=0.04, alpha=0.12)


@dataclass(frozen=True)
class SampleSphere:
    """A homogeneous sphere of known ``radius_mm`` made of one ``material`` (a BRDF): the
    curved, homogeneous sample passive reflectometry needs (Romeiro et al. 2008 Sec. 3)."""

    radius_mm: float = 30.0
    material: BRDF = SAMPLE_MATERIAL

    def __post_init__(self) -> None:
        if not self.radius_mm > 0:
            raise ValueError(f"SampleSphere.radius_mm must be > 0, got {self.radius_mm!r}")
        if not isinstance(self.material, BRDF):
            raise TypeError(f"SampleSphere.material must be a reconstruct BRDF, got {type(self.material).__name__}")

    def scene_object(self, center_mm, name: str = "sample_sphere") -> SceneObject:
        c = np.asarray(center_mm, dtype=np.float64)
        if c.shape != (3,):
            raise ValueError(f"center_mm must be a 3-vector (world, mm), got shape {c.shape}")
        return SceneObject(Sphere(self.radius_mm, c), self.material, name)


@dataclass(frozen=True)
class SphereRow:
    """Collinear, equally spaced steel spheres on a fixture (Lensch et al. 2003, Sec. 4.1: six
    bearing balls on a CNC-milled bar): centre i = ``start_mm + i * spacing_mm * direction``."""

    count: int = 6
    radius_mm: float = 10.0
    spacing_mm: float = 40.0
    kind: str = "steel"

    def __post_init__(self) -> None:
        if int(self.count) < 3:
            raise ValueError(f"count must be >= 3 (the light is triangulated from >= 3 spheres), got {self.count!r}")
        if not self.spacing_mm > 2 * self.radius_mm:
            raise ValueError(f"spacing_mm must exceed the diameter {2 * self.radius_mm} mm, got {self.spacing_mm!r}")
        CalibrationSphere(self.radius_mm, self.kind)

    def centers(self, start_mm, direction) -> np.ndarray:
        """World centres (count, 3) mm of a row starting at ``start_mm`` along ``direction``."""
        d = np.asarray(direction, dtype=np.float64)
        if d.shape != (3,) or np.linalg.norm(d) == 0:
            raise ValueError(f"direction must be a non-zero 3-vector, got {direction!r}")
        d = d / np.linalg.norm(d)
        return np.asarray(start_mm, float) + np.arange(int(self.count))[:, None] * self.spacing_mm * d

    def scene_objects(self, start_mm, direction) -> list[SceneObject]:
        ball = CalibrationSphere(self.radius_mm, self.kind)
        return [ball.scene_object(c, f"{self.kind}_sphere_{i}")
                for i, c in enumerate(self.centers(start_mm, direction))]


# ----------------------------------------------------------------------------------------------
# environments
# ----------------------------------------------------------------------------------------------
def environment(name: str = "grace", *, data_dir: str | Path | None = None) -> EnvironmentMap:
    """An environment map in the world frame (lat-long, row 0 = +z).

    ``name``: one of ``PROBES`` (the real HDR light probes in ``<shared data>/probes/NAME.hdr``,
    read with OpenCV; falls back to the procedural sky with a warning when the data folder is
    absent) or ``"sky"`` (:func:`procedural_sky`).
    """
    if name == "sky":
        return procedural_sky()
    if name not in PROBES:
        raise ValueError(f"environment must be one of {PROBES + ('sky',)}, got {name!r}")
    base = Path(data_dir) if data_dir is not None else shared_data_dir()
    path = None if base is None else base / "probes" / f"{name}.hdr"
    if path is None or not path.is_file():
        warnings.warn(f"light probe {name!r} not found (looked for {path}); using the procedural sky",
                      RuntimeWarning, stacklevel=2)
        return procedural_sky()
    return EnvironmentMap.load(path)


def procedural_sky(*, sun_azimuth_deg: float = 135.0, sun_elevation_deg: float = 40.0,
                   sun_radiance: float = 2000.0, sun_radius_deg: float = 2.0,
                   height: int = 128) -> EnvironmentMap:
    """A clear-sky lat-long map (world frame, +z zenith): blue zenith fading to a bright horizon,
    a sun disc (``sun_radius_deg``, radiance ``sun_radiance``) with a forward-scattering glow, and
    a uniform brown ground below the horizon. Linear RGB radiance, arbitrary units (sky ~ 1)."""
    if not -90 <= sun_elevation_deg <= 90:
        raise ValueError(f"sun_elevation_deg must be in [-90, 90], got {sun_elevation_deg!r}")
    az, el = np.radians(sun_azimuth_deg), np.radians(sun_elevation_deg)
    sun = np.array([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)])
    zenith = np.array([0.25, 0.45, 1.0])
    horizon = np.array([0.9, 0.95, 1.0])
    ground = np.array([0.16, 0.12, 0.08])

    def radiance(d):
        up = np.clip(d[:, 2], 0, 1)[:, None]
        sky = horizon + (zenith - horizon) * np.sqrt(up)
        cos_sun = d @ sun
        glow = 0.6 * np.exp((cos_sun[:, None] - 1.0) * 12.0)
        disc = np.where(cos_sun > np.cos(np.radians(sun_radius_deg)), sun_radiance, 0.0)[:, None]
        return np.where(d[:, 2:3] >= 0, sky + glow + disc, ground)

    return EnvironmentMap.from_function(radiance, height)
