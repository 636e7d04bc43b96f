"""Calibration-target detection: chessboards and ChArUco boards.

All detectors return a :class:`TargetDetection` with image points shaped (N, 2) — OpenCV 5
returns (N, 2) where 4.x returned (N, 1, 2); :func:`as_points2d` is the one place that
normalises this. Pixel coordinates: x right, y down, pixel centres at integers (OpenCV).
Board coordinates: the board's own frame, z = 0 on the board, in the unit of ``square_size``
(millimetres by convention).
"""
from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from . import _validate
from .errors import InvalidInput, TargetNotFound

__all__ = [
    "TargetDetection", "as_points2d", "chessboard_object_points", "detect_chessboard",
    "make_charuco_board", "detect_charuco", "to_gray_u8",
]


@dataclass(frozen=True)
class TargetDetection:
    """Corners of one calibration target found in one image.

    Attributes
    ----------
    image_points : ndarray of shape (N, 2), float64
        Corner positions, pixels (x right, y down).
    object_points : ndarray of shape (N, 3), float64
        The same corners in the board frame (z = 0), units of the square size (mm).
    image_size : tuple of int
        ``(width, height)`` of the image, pixels.
    ids : ndarray of shape (N,) or None
        ChArUco corner ids (None for a chessboard, whose corners are all present in order).
    frame : str or None
        Name of the frame the detection came from (used in error messages and reports).
    """

    image_points: np.ndarray
    object_points: np.ndarray
    image_size: tuple[int, int]
    ids: np.ndarray | None = None
    frame: str | None = None


def as_points2d(points, *, arg_name: str = "points") -> np.ndarray:
    """Normalise OpenCV corner arrays ((N, 2) in 5.x, (N, 1, 2) in 4.x) to float64 (N, 2)."""
    arr = np.asarray(points, dtype=np.float64)
    if arr.ndim == 3 and arr.shape[1:] == (1, 2):
        arr = arr[:, 0, :]
    if arr.ndim != 2 or arr.shape[1] != 2:
        raise InvalidInput(f"{arg_name} must have shape (N, 2) or (N, 1, 2), got {arr.shape}")
    return arr


#: Rec. 601 luma weights (R, G, B)
_LUMA = (0.299, 0.587, 0.114)


def to_gray_u8(image, *, white_percentile: float = 100.0, arg_name: str = "image") -> np.ndarray:
    """An 8-bit grey view of ``image`` (H, W) or (H, W, 3) RGB, any dtype, for the detectors.

    Non-8-bit images are scaled so their ``white_percentile`` percentile maps to 255 (detectors
    need contrast, not radiometry; below 100 hot pixels and highlights of a linear HDR image
    do not crush the rest).
    """
    img = _validate.image(image, arg_name)
    if img.dtype == np.uint8 and img.ndim == 2:
        return img
    if not 0 < white_percentile <= 100:
        raise InvalidInput(f"white_percentile must be in (0, 100], got {white_percentile!r}",
                           argument="white_percentile")
    img = _validate.gray(img, arg_name, weights=_LUMA, dtype=np.float32)
    top = float(img.max() if white_percentile == 100 else np.percentile(img, white_percentile))
    if top <= 0:
        return np.zeros(img.shape, np.uint8)
    scale = 255.0 / top if top > 255 or img.dtype.kind == "f" else 1.0
    return np.clip(img * scale + 0.5, 0, 255).astype(np.uint8)


def chessboard_object_points(pattern_size: tuple[int, int], square_size: float = 1.0) -> np.ndarray:
    """Board-frame corners of a chessboard with ``pattern_size = (cols, rows)`` inner corners.

    Returns
    -------
    ndarray of shape (cols * rows, 3)
        Row-major (x fastest), the order OpenCV's detectors report, z = 0, units of
        ``square_size``.
    """
    cols, rows = _pattern(pattern_size)
    if not square_size > 0:
        raise InvalidInput(f"square_size must be positive, got {square_size}")
    grid = np.zeros((rows * cols, 3))
    grid[:, :2] = np.mgrid[0:cols, 0:rows].T.reshape(-1, 2) * float(square_size)
    return grid


def _pattern(pattern_size) -> tuple[int, int]:
    try:
        cols, rows = (int(v) for v in pattern_size)
    except (TypeError, ValueError):
        raise InvalidInput(f"pattern_size must be (cols, rows) inner corners, got {pattern_size!r}") from None
    if cols < 2 or rows < 2:
        raise InvalidInput(f"pattern_size must be at least (2, 2) inner corners, got {(cols, rows)}")
    return cols, rows


def detect_chessboard(image, pattern_size: tuple[int, int], square_size: float = 1.0, *,
                      frame: str | None = None, method: str = "sb") -> TargetDetection:
    """Find the inner corners of a chessboard.

    Parameters
    ----------
    image : ndarray of shape (H, W) or (H, W, 3)
        The photo (any dtype; converted to 8-bit grey for detection).
    pattern_size : (int, int)
        Inner corners ``(cols, rows)``, e.g. ``(9, 6)``.
    square_size : float
        Side of one square, mm (sets the unit of ``object_points``).
    frame : str, optional
        Name of the frame, used in the error message if no board is found.
    method : {'sb', 'sb_accuracy', 'classic'}
        ``'sb'`` (default, the most accurate measured: ``benchmarks/chessboard_corners.py``):
        ``cv2.findChessboardCornersSB`` (sector-based; robust to blur and perspective), then
        ``cv2.cornerSubPix`` with a window that fits the squares: corner RMS 0.042 / 0.053 px
        on independent renders (noise 1 / 2.5 DN), 0.038-0.049 px on close sharp boards;
        OpenCV's left*.jpg calibrate to RMS 0.1952 px with K within 0.05 px of OpenCV's own.
        ``'sb_accuracy'``: the same detector with ``CALIB_CB_ACCURACY`` (its own refinement)
        instead: measured worse here (0.090 / 0.087 px; 0.20-0.39 px on close sharp boards;
        left*.jpg RMS 0.2560 px, fx 0.9 px off) and 4x slower. ``'classic'``:
        ``cv2.findChessboardCorners`` + ``cv2.cornerSubPix`` (5x5 window), the recipe OpenCV's
        own calibration test uses (0.042 / 0.053 px, left*.jpg 0.1962 px; less robust to blur).

    Returns
    -------
    TargetDetection

    Raises
    ------
    TargetNotFound
        The full board was not found in the image (names ``frame``).
    """
    cols, rows = _pattern(pattern_size)
    gray = to_gray_u8(image)
    if method in ("sb", "sb_accuracy"):
        flags = cv2.CALIB_CB_NORMALIZE_IMAGE | (cv2.CALIB_CB_ACCURACY if method == "sb_accuracy" else 0)
        found, corners = cv2.findChessboardCornersSB(gray, (cols, rows), flags=flags)
        if not found:  # the exhaustive search is several times slower: only when needed
            found, corners = cv2.findChessboardCornersSB(gray, (cols, rows),
                                                         flags=flags | cv2.CALIB_CB_EXHAUSTIVE)
    elif method == "classic":
        found, corners = cv2.findChessboardCorners(gray, (cols, rows))
        if found:
            corners = cv2.cornerSubPix(gray, corners.reshape(-1, 1, 2).astype(np.float32), (5, 5),
                                       (-1, -1),
                                       (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_COUNT, 30, 0.1))
    else:
        raise InvalidInput(f"method must be 'sb_accuracy', 'sb' or 'classic', got {method!r}")
    if not found or corners is None:
        raise TargetNotFound(f"no {cols}x{rows} chessboard found", frame=frame)
    pts = as_points2d(corners, arg_name="corners")
    if method == "sb":
        # A saddle-point refinement roughly halves SB's corner error on sharp prints (synthetic
        # boards: 0.07-0.11 -> 0.03-0.04 px); the window stays inside a quarter of the smallest
        # square so it never reaches a neighbouring corner.
        grid = pts.reshape(rows, cols, 2)
        spacing = min(np.linalg.norm(np.diff(grid, axis=0), axis=2).min(),
                      np.linalg.norm(np.diff(grid, axis=1), axis=2).min())
        half = int(np.clip(0.3 * spacing, 2, 5))
        pts = cv2.cornerSubPix(gray, pts.astype(np.float32).reshape(-1, 1, 2), (half, half), (-1, -1),
                               (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_COUNT, 30, 0.01)).reshape(-1, 2)
        pts = pts.astype(np.float64)
    return TargetDetection(pts, chessboard_object_points((cols, rows), square_size),
                           (gray.shape[1], gray.shape[0]), None, frame)


_DICTS = {name: getattr(cv2.aruco, name) for name in dir(cv2.aruco) if name.startswith("DICT_")}


def make_charuco_board(squares: tuple[int, int] = (7, 5), square_size: float = 20.0,
                       marker_size: float = 15.0, dictionary: str = "DICT_5X5_100"):
    """A ChArUco board (``cv2.aruco.CharucoBoard``).

    Parameters
    ----------
    squares : (int, int)
        Squares ``(cols, rows)``; the board has ``(cols-1)*(rows-1)`` inner (ChArUco) corners.
    square_size, marker_size : float
        Chessboard square and ArUco marker side, mm (``marker_size < square_size``).
    dictionary : str
        Name of a predefined ArUco dictionary, e.g. ``'DICT_5X5_100'``.
    """
    if dictionary not in _DICTS:
        raise InvalidInput(f"dictionary must be a cv2.aruco DICT_* name, got {dictionary!r}")
    cols, rows = _pattern(squares)
    if not 0 < marker_size < square_size:
        raise InvalidInput(f"marker_size must be in (0, square_size={square_size}), got {marker_size}")
    aruco_dict = cv2.aruco.getPredefinedDictionary(_DICTS[dictionary])
    return cv2.aruco.CharucoBoard((cols, rows), float(square_size), float(marker_size), aruco_dict)


#: cornerSubPix half-window limits for ChArUco corners, pixels (OpenCV's own examples use 5)
CHARUCO_WINDOW_PX = (2, 5)


def _charuco_window(board, object_points: np.ndarray, image_points: np.ndarray) -> tuple[int, int]:
    """cornerSubPix half-window (pixels) that keeps the window inside the white gap between a
    corner and the markers beside it, at the most foreshortened corner of this view (the
    board -> image homography's smaller local scale), within :data:`CHARUCO_WINDOW_PX`."""
    lo, hi = CHARUCO_WINDOW_PX
    if len(image_points) < 4:
        return hi, hi
    H, _ = cv2.findHomography(object_points[:, :2], image_points)
    if H is None:
        return hi, hi
    x, y = object_points[:, 0], object_points[:, 1]
    w = H[2, 0] * x + H[2, 1] * y + H[2, 2]
    u = (H[0, 0] * x + H[0, 1] * y + H[0, 2]) / w
    v = (H[1, 0] * x + H[1, 1] * y + H[1, 2]) / w
    # Jacobian of the homography at each corner, (N, 2, 2): d(u, v) / d(x, y)
    J = np.stack([np.stack([(H[0, 0] - u * H[2, 0]) / w, (H[0, 1] - u * H[2, 1]) / w], -1),
                  np.stack([(H[1, 0] - v * H[2, 0]) / w, (H[1, 1] - v * H[2, 1]) / w], -1)], -2)
    px_per_mm = float(np.linalg.svd(J, compute_uv=False)[:, -1].min())
    gap_px = (board.getSquareLength() - board.getMarkerLength()) / 2 * px_per_mm
    half = int(np.clip(np.floor(gap_px), lo, hi))
    return half, half


def detect_charuco(image, board, *, frame: str | None = None, min_corners: int = 6) -> TargetDetection:
    """Find the ChArUco corners of ``board`` in ``image``.

    Parameters
    ----------
    image : ndarray of shape (H, W) or (H, W, 3)
        The photo.
    board : cv2.aruco.CharucoBoard
        The board (see :func:`make_charuco_board`).
    frame : str, optional
        Frame name for error messages.
    min_corners : int
        Fewest interpolated corners accepted (a pose needs >= 4 non-collinear; 6 is safer).

    Returns
    -------
    TargetDetection
        With ``ids`` (N,) and ``object_points`` from ``board.getChessboardCorners()``, mm.

    Raises
    ------
    TargetNotFound
        Fewer than ``min_corners`` corners found (names ``frame``).
    """
    if not isinstance(board, cv2.aruco.CharucoBoard):
        raise InvalidInput(f"board must be a cv2.aruco.CharucoBoard (see make_charuco_board), "
                           f"got {type(board).__name__}", argument="board")
    gray = to_gray_u8(image)
    detector = cv2.aruco.CharucoDetector(board)
    corners, ids, _marker_corners, _marker_ids = detector.detectBoard(gray)
    n = 0 if ids is None else len(ids)
    if n < min_corners:
        raise TargetNotFound(f"ChArUco board: {n} corners found, need {min_corners}", frame=frame)
    ids = np.asarray(ids).ravel().astype(np.int64)
    obj = np.asarray(board.getChessboardCorners(), dtype=np.float64).reshape(-1, 3)[ids]
    if min(len(np.unique(obj[:, 0])), len(np.unique(obj[:, 1]))) < 2:
        # corners along one row or column fix no homography (calibrateCamera's start fails on them)
        raise TargetNotFound(f"ChArUco board: the {n} corners found lie in one row or column", frame=frame)
    # The detector's own interpolation leaves ~0.25 px errors; a saddle-point refinement on the
    # image itself brings them to the chessboard detector's level, with a window that stays off
    # the markers (a window reaching their edges biases the saddle: 0.30 -> 0.21 px rms on a
    # 320 x 240 render of the demo's board)
    corners = cv2.cornerSubPix(gray, as_points2d(corners).astype(np.float32).reshape(-1, 1, 2),
                               _charuco_window(board, obj, as_points2d(corners)), (-1, -1),
                               (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_COUNT, 50, 0.001))
    return TargetDetection(as_points2d(corners, arg_name="corners"), obj,
                           (gray.shape[1], gray.shape[0]), ids, frame)
