"""Hand-held (or tripod) board views for the camera intrinsics: where a careful operator holds
the board, view by view, and the pose that puts it there.

Zhang (1999) needs planar views that tilt about both image axes; the principal point and the
distortion also need the board near the image's corners and edges. The view sequence
(:func:`handheld_view`) is one procedure for the operator's prompt (``capture.plan``) and for
the simulated lab's staging (:func:`handheld_board_pose`), so a resumed session stages view k
the same way. Frames: camera frame OpenCV (x right, y down, z forward), pixels x right, y down;
mm. Pure numpy (the plan module imports this without the renderer).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

#: where view k puts the board in the frame (the corners first, so that even a few views cover
#: them), as words for the operator and as the direction (ax, ay) in [-1, 1]^2 the board is
#: pushed to (x right, y down; 0: centred)
HANDHELD_PLACES = (("in the top-left corner", (-1, -1)), ("in the bottom-right corner", (1, 1)),
                   ("in the top-right corner", (1, -1)), ("in the bottom-left corner", (-1, 1)),
                   ("in the centre", (0, 0)), ("at the top edge", (0, -1)), ("at the right edge", (1, 0)),
                   ("at the bottom edge", (0, 1)), ("at the left edge", (-1, 0)))
#: how far each view tilts the board, degrees: strong tilts pin the focal length and principal
#: point (45° held the ChArUco corners' detection on a 320 x 240 frame)
HANDHELD_TILT_DEG = 45.0
#: the untilted board's width as a fraction of the image width (its markers stay detectable on
#: a 320 x 240 frame while the pushed board still reaches the corners)
HANDHELD_WIDTH_FRACTION = 0.75
# the edge of the board that leans away, for tilt axes at 0, 45, 90 ... degrees (see below)
_LEAN_WORDS = ("bottom edge", "bottom-left corner", "left edge", "top-left corner", "top edge",
               "top-right corner", "right edge", "bottom-right corner")


@dataclass(frozen=True)
class HandheldView:
    """Hand-held board view ``view`` (0-based) of ``views``: the board tilted by ``tilt_deg``
    about the image-plane axis at ``tilt_axis_deg`` from the image x axis (the axis turns by
    360°/``views`` from view to view, so the tilts are about both image axes, each sign; turned
    round by 180° where the side leaning away would face the frame's edge), pushed towards
    ``anchor`` (ax, ay) in [-1, 1]^2 of the frame (``place`` in words), all of it in view."""

    view: int
    views: int
    anchor: tuple[float, float]
    place: str
    tilt_axis_deg: float
    tilt_deg: float

    @property
    def prompt(self) -> str:
        """The operator's instruction for this view."""
        # tilting about the axis at angle phi sends the board's edge towards (-sin phi, cos phi) away
        lean = _LEAN_WORDS[int(round(self.tilt_axis_deg / 45.0)) % 8]
        return (f"view {self.view + 1} of {self.views}: hold the board {self.place} of the frame, "
                f"tilted about {self.tilt_deg:g}° with its {lean} away from the camera, filling about "
                "three quarters of the frame's width, all of it in view (the views together cover "
                "the whole frame, corners included)")

    def pose_options(self) -> dict:
        """Keyword arguments of :func:`handheld_board_pose` for this view."""
        return {"anchor": self.anchor, "tilt_axis_deg": self.tilt_axis_deg, "tilt_deg": self.tilt_deg}


def handheld_view(view: int, views: int) -> HandheldView:
    """View ``view`` (0-based) of ``views`` (see :class:`HandheldView`). Raises ValueError for
    a view outside 0..views-1."""
    if not (isinstance(views, (int, np.integer)) and not isinstance(views, bool) and views >= 1):
        raise ValueError(f"views must be a whole number >= 1, got {views!r}")
    if not (isinstance(view, (int, np.integer)) and not isinstance(view, bool) and 0 <= view < views):
        raise ValueError(f"view must be a whole number in 0..{views - 1}, got {view!r}")
    place, anchor = HANDHELD_PLACES[view % len(HANDHELD_PLACES)]
    phi = 360.0 * view / views
    away = np.array([-np.sin(np.radians(phi)), np.cos(np.radians(phi))])  # the edge that leans away
    if away @ np.asarray(anchor, float) > 1e-9:
        # near the frame's edge the board's far side would be small and squeezed by the lens: turn
        # the tilt round so the near side is there (the tilt axes still turn through 180°)
        phi = (phi + 180.0) % 360.0
    return HandheldView(int(view), int(views), anchor, place, phi, HANDHELD_TILT_DEG)


def handheld_board_pose(board, camera, *, anchor=(0.0, 0.0), tilt_axis_deg: float = 0.0,
                        tilt_deg: float = HANDHELD_TILT_DEG, width_fraction: float = HANDHELD_WIDTH_FRACTION,
                        margin_fraction: float = 0.04) -> np.ndarray:
    """Board -> world pose (4x4, mm) of a sheet held in front of ``camera`` (a hand-held or
    tripod view for the intrinsics, Zhang 1999).

    The sheet starts facing the camera square on, at the depth where its width spans
    ``width_fraction`` of the image; it is tilted by ``tilt_deg`` about the image-plane axis at
    ``tilt_axis_deg`` from the image x axis (its edge towards (-sin, cos) of that angle, x right
    and y down, goes away from the camera), then slid parallel to the image so that its image
    bounding box is pushed towards ``anchor`` = (ax, ay) in [-1, 1]^2 (-1: against the left /
    top edge, 0: centred, 1: right / bottom), the whole sheet ``margin_fraction`` of the image
    width inside the frame (pinhole projection; the lens's barrel distortion only pulls the
    corners in).

    Parameters
    ----------
    board : sims.targets.PrintedBoard
        The sheet (its whole ``extent_mm`` stays in view).
    camera : reconstruct.camera.CameraModel
        K, image size and the world -> camera pose.
    anchor : (float, float)
        Where in the frame the sheet goes (above).
    tilt_axis_deg, tilt_deg : float
        The tilt (above), degrees.
    width_fraction, margin_fraction : float
        Size of the untilted sheet and the margin, as fractions of the image width.

    Returns
    -------
    ndarray of shape (4, 4)
        Board frame -> world frame (the board frame of :mod:`sims.targets`: z into the sheet,
        away from the camera).

    Raises
    ------
    ValueError
        For an ``anchor`` outside [-1, 1]^2 or a sheet that cannot fit in the frame.
    """
    a = np.asarray(anchor, float)
    if a.shape != (2,) or not np.all(np.abs(a) <= 1):
        raise ValueError(f"anchor must be (ax, ay) in [-1, 1]^2, got {anchor!r}")
    if not 0 < width_fraction < 1 - 2 * margin_fraction:
        raise ValueError(f"width_fraction must lie in (0, {1 - 2 * margin_fraction:g}), got {width_fraction!r}")
    phi, t = np.radians(tilt_axis_deg), np.radians(tilt_deg)
    k = np.array([[0.0, 0.0, np.sin(phi)], [0.0, 0.0, -np.cos(phi)], [-np.sin(phi), np.cos(phi), 0.0]])
    R = np.eye(3) + np.sin(t) * k + (1 - np.cos(t)) * k @ k   # board -> camera (Rodrigues)
    x0, y0, x1, y1 = board.extent_mm
    sheet = np.array([[x0, y0, 0], [x1, y0, 0], [x1, y1, 0], [x0, y1, 0]], float) - board.center_mm
    f, c = camera.K[0, 0], camera.K[:2, 2]
    size = np.array([camera.width, camera.height], float) - 1
    z = f * (x1 - x0) / (width_fraction * (size[0] + 1))
    margin = margin_fraction * (size[0] + 1)
    centre = np.array([0.0, 0.0, z])
    for _ in range(8):  # perspective makes the placement a fixed point; it settles in a few rounds
        p = sheet @ R.T + centre
        uv = f * p[:, :2] / p[:, 2:] + c
        lo, span = uv.min(axis=0), np.ptp(uv, axis=0)
        room = size - 2 * margin - span
        if np.any(room < 0):
            raise ValueError(f"the board does not fit in the frame at width_fraction={width_fraction!r}, "
                             f"tilt_deg={tilt_deg!r}")
        centre[:2] += (margin + (a + 1) / 2 * room - lo) * centre[2] / f
    board_cam, world_cam = np.eye(4), np.eye(4)
    board_cam[:3, :3], board_cam[:3, 3] = R, centre
    world_cam[:3, :3], world_cam[:3, 3] = camera.R, camera.t
    return board.centered_pose(np.linalg.inv(world_cam) @ board_cam)
