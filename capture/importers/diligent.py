"""Multi-light image sets in the DiLiGenT layout -> a session of the store.

The layout (Shi et al., "A Benchmark Dataset and Evaluation for Non-Lambertian and Uncalibrated
Photometric Stereo", CVPR 2016), one folder per object:

    filenames.txt           the K image names, in light order
    001.png ...             K images (8- or 16-bit RGB PNG, linear), one per light
    light_directions.txt    K rows "x y z": unit vectors towards each (distant) light
    light_intensities.txt   K rows "r g b": each light's intensity (divide the image by its row)
    mask.png                the object's pixels (non-zero), same size as the images
    Normal_gt.mat           optional: MATLAB ``Normal_gt`` (H, W, 3) ground-truth normals

Frames: DiLiGenT's camera frame is x right, y up, z towards the camera (orthographic view along
-z). gonio uses OpenCV's camera frame (x right, y down, z forward), so y and z of the lights and
normals are negated on reading: a light on the camera's side has ``l_z < 0`` and a surface facing
the camera ``n_z < 0``, as in :mod:`reconstruct.photometric_stereo`.

:func:`read_diligent` checks the whole set before anything is written (every listed image
present and decodable at one size, one light row per image, a binary mask of the images' size
with pixels in it, ground truth of that size) and raises :class:`DiligentFormatError` naming
the file and what is wrong. :func:`import_diligent` then records it as a session: one step and
one frame (the file's own bytes) per image, the mask and the ground truth as frames of their own
steps, the given lights and the orthographic camera as calibration results, the source folder
and every file's SHA-256 in the plan (provenance). :func:`read_imported_session` reads it back.
"""
from __future__ import annotations

import hashlib
import io
import json
import os
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
import scipy.io

from ..events import Event, EventKind
from ..store import SessionExists, SessionNotFound, Store, check_session_name

FORMAT = "diligent"
#: Step kinds of an imported session.
LIGHT_STEP, MASK_STEP, TRUTH_STEP = "imported_light", "imported_mask", "imported_ground_truth"
#: DiLiGenT (x right, y up, z to the camera) -> OpenCV camera frame (x right, y down, z forward).
_FLIP = np.array([1.0, -1.0, -1.0])
CITATION = ("Shi et al., A Benchmark Dataset and Evaluation for Non-Lambertian and Uncalibrated "
            "Photometric Stereo, CVPR 2016 / TPAMI 2019")


class DiligentFormatError(ValueError):
    """The folder is not a usable DiLiGenT-layout set; the message names the file and the fault."""


@dataclass(frozen=True)
class MultiLightSet:
    """Images of one object under K distant lights, seen by an orthographic camera.

    Attributes
    ----------
    name : str
        The object (the folder's name).
    images : ndarray (K, H, W, 3), uint8 or uint16
        The images as stored, RGB, linear in radiance.
    full_scale : float
        The images' largest code (255 or 65535): ``images / full_scale`` is in [0, 1].
    light_directions : ndarray (K, 3)
        Unit vectors from the surface towards each light, OpenCV camera frame.
    light_intensities : ndarray (K, 3)
        Each light's RGB intensity (relative).
    mask : ndarray (H, W) bool
        The object's pixels.
    normals_gt : ndarray (H, W, 3) or None
        Ground-truth unit normals, OpenCV camera frame (zero outside the mask); for scoring only.
    filenames : tuple of str
        The image files, in light order.
    held_out : ndarray (K,) bool
        Lights kept from every fit and used only to score relighting.
    """

    name: str
    images: np.ndarray
    full_scale: float
    light_directions: np.ndarray
    light_intensities: np.ndarray
    mask: np.ndarray
    normals_gt: np.ndarray | None
    filenames: tuple
    held_out: np.ndarray

    #: the direction from every surface point towards the orthographic camera, OpenCV frame
    view_direction = np.array([0.0, 0.0, -1.0])

    def radiance(self, lights=None) -> np.ndarray:
        """Images divided by full scale and by their light's intensity, float32 (k, H, W, 3):
        reflected radiance per unit irradiance up to one common factor, i.e.
        ``f_r cos(theta_i)`` x that factor. ``lights`` selects images (default all)."""
        sel = slice(None) if lights is None else lights
        e = self.light_intensities[sel].astype(np.float32)
        return self.images[sel].astype(np.float32) / np.float32(self.full_scale) / e[:, None, None, :]


def _sha256(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def _rows(path: Path, K: int, what: str) -> np.ndarray:
    if not path.is_file():
        raise DiligentFormatError(f"{path}: missing ({what}, one row per image)")
    try:
        a = np.loadtxt(path, ndmin=2)
    except ValueError as exc:
        raise DiligentFormatError(f"{path}: not a table of numbers ({exc})") from None
    if a.shape != (K, 3):
        raise DiligentFormatError(f"{path}: {a.shape[0]} rows of {a.shape[1]} numbers; expected "
                                  f"{K} rows of 3 ({what}), one per image of filenames.txt")
    if not np.all(np.isfinite(a)):
        raise DiligentFormatError(f"{path}: holds non-finite values")
    return a


def _decode(path: Path) -> np.ndarray:
    img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if img is None:
        raise DiligentFormatError(f"{path}: not a readable image")
    return img


def read_diligent(folder, *, hold_out_every: int = 4) -> MultiLightSet:
    """Read and check a DiLiGenT-layout folder (see the module docstring).

    ``hold_out_every``: every n-th light (the 4th, 8th, ...) is marked held out; 0 = none.
    Raises :class:`DiligentFormatError` on any fault, before anything is written anywhere.
    """
    d = Path(folder)
    if not d.is_dir():
        raise DiligentFormatError(f"{d}: not a folder")
    names_file = d / "filenames.txt"
    if not names_file.is_file():
        raise DiligentFormatError(f"{names_file}: missing (the image names, one per line, in "
                                  "light order)")
    names = [n.strip() for n in names_file.read_text().splitlines() if n.strip()]
    if len(names) < 3:
        raise DiligentFormatError(f"{names_file}: lists {len(names)} images; photometric stereo "
                                  "needs at least 3 lights")
    missing = [n for n in names if not (d / n).is_file() or Path(n).name != n]
    if missing:
        raise DiligentFormatError(f"{d}: {len(missing)} of the {len(names)} images listed in "
                                  f"filenames.txt are missing: {', '.join(missing[:5])}"
                                  + (" ..." if len(missing) > 5 else ""))
    K = len(names)
    dirs = _rows(d / "light_directions.txt", K, "unit light directions")
    norms = np.linalg.norm(dirs, axis=1)
    bad = np.flatnonzero(np.abs(norms - 1) > 0.01)
    if len(bad):
        raise DiligentFormatError(f"{d / 'light_directions.txt'}: row {bad[0] + 1} has length "
                                  f"{norms[bad[0]]:.3f}, not a unit vector")
    if np.linalg.matrix_rank(dirs, tol=1e-3) < 3:
        raise DiligentFormatError(f"{d / 'light_directions.txt'}: the directions lie in one plane; "
                                  "normals are not determined")
    intens = _rows(d / "light_intensities.txt", K, "RGB light intensities")
    if np.any(intens <= 0):
        raise DiligentFormatError(f"{d / 'light_intensities.txt'}: row "
                                  f"{np.flatnonzero(np.any(intens <= 0, axis=1))[0] + 1} has an "
                                  "intensity <= 0")
    first = _decode(d / names[0])
    if first.ndim != 3 or first.shape[2] != 3 or first.dtype not in (np.uint8, np.uint16):
        raise DiligentFormatError(f"{d / names[0]}: expected an 8- or 16-bit RGB image, got shape "
                                  f"{first.shape} {first.dtype}")
    images = np.empty((K, *first.shape), first.dtype)
    for k, n in enumerate(names):
        img = first if k == 0 else _decode(d / n)
        if img.shape != first.shape or img.dtype != first.dtype:
            raise DiligentFormatError(f"{d / n}: {img.shape} {img.dtype}, but {names[0]} is "
                                      f"{first.shape} {first.dtype}; all images must match")
        images[k] = img[..., ::-1]  # OpenCV decodes BGR
    H, W = first.shape[:2]
    mask = _read_mask(d / "mask.png", (H, W))
    normals = _read_truth(d / "Normal_gt.mat", (H, W), mask)
    held = np.zeros(K, bool)
    if hold_out_every:
        if hold_out_every < 2:
            raise DiligentFormatError(f"hold_out_every must be 0 or >= 2, got {hold_out_every}")
        held[hold_out_every - 1::hold_out_every] = True
    return MultiLightSet(name=d.resolve().name, images=images,
                         full_scale=float(np.iinfo(first.dtype).max),
                         light_directions=dirs / norms[:, None] * _FLIP, light_intensities=intens,
                         mask=mask, normals_gt=normals, filenames=tuple(names), held_out=held)


def _read_mask(path: Path, shape) -> np.ndarray:
    if not path.is_file():
        raise DiligentFormatError(f"{path}: missing (the object's pixels)")
    m = _decode(path)
    if m.ndim == 3:
        if np.any(m != m[..., :1]):
            raise DiligentFormatError(f"{path}: a colour image; a mask is grey (0 outside the object)")
        m = m[..., 0]
    if m.shape != shape:
        raise DiligentFormatError(f"{path}: {m.shape[1]} x {m.shape[0]} px, the images are "
                                  f"{shape[1]} x {shape[0]}")
    values = np.unique(m)
    if len(values) > 2:
        raise DiligentFormatError(f"{path}: {len(values)} grey levels; a mask holds two (0 outside, "
                                  "one value inside)")
    mask = m > 0
    if mask.sum() < 3:
        raise DiligentFormatError(f"{path}: {int(mask.sum())} object pixels; the mask is empty")
    return mask


def _read_truth(path: Path, shape, mask) -> np.ndarray | None:
    if not path.is_file():
        return None
    try:
        n = scipy.io.loadmat(str(path)).get("Normal_gt")
    except Exception as exc:  # scipy raises several types for damaged files
        raise DiligentFormatError(f"{path}: not a readable MATLAB file ({exc})") from None
    if n is None or n.shape != (*shape, 3):
        raise DiligentFormatError(f"{path}: needs a variable Normal_gt of shape {(*shape, 3)}, got "
                                  f"{None if n is None else n.shape}")
    n = np.asarray(n, np.float64) * _FLIP
    inside = n[mask]
    off = np.abs(np.linalg.norm(inside, axis=1) - 1) > 0.01
    if not np.all(np.isfinite(inside)) or off.mean() > 0.01:
        raise DiligentFormatError(f"{path}: {int(off.sum())} of the mask's normals are not unit "
                                  "vectors")
    return np.where(mask[..., None], n, 0.0)


# ----------------------------------------------------------------------------------------------
# the store
# ----------------------------------------------------------------------------------------------
def import_diligent(folder, store: Store | str | os.PathLike, session: str | None = None, *,
                    hold_out_every: int = 4, operator: str = "") -> str:
    """Record a DiLiGenT-layout folder as a session of ``store`` (a :class:`Store`, or the path
    of one, created if absent); returns the session's name (default ``diligent-<object>``).

    The set is checked completely first (:class:`DiligentFormatError`), and the session name
    and an existing session refused, before the store is opened or created: a bad set or name
    writes nothing. An import of the same files cut short (Ctrl-C, a full disk: the session is
    left ``paused``) is continued from its first file not stored."""
    d = Path(folder)
    data = read_diligent(d, hold_out_every=hold_out_every)
    name = check_session_name(session or f"diligent-{data.name}")
    files = [*data.filenames, "mask.png", "light_directions.txt", "light_intensities.txt",
             "filenames.txt"] + (["Normal_gt.mat"] if data.normals_gt is not None else [])
    H, W = data.mask.shape
    plan = {"imported": {
        "format": FORMAT, "source": str(d.resolve()), "object": data.name, "citation": CITATION,
        "lights": len(data.filenames), "held_out_every": hold_out_every,
        "image_size_px": [W, H], "bit_depth": 8 if data.full_scale == 255 else 16,
        "frame": "OpenCV camera frame (x right, y down, z forward); DiLiGenT's y and z negated",
        "camera": {"model": "orthographic", "view_direction": data.view_direction.tolist()},
        "sha256": {f: _sha256(d / f) for f in files}}}
    plan_hash = hashlib.sha256(json.dumps(plan, sort_keys=True).encode()).hexdigest()
    steps = [{"kind": LIGHT_STEP, "file": f, "light_direction": data.light_directions[k].tolist(),
              "light_intensity": data.light_intensities[k].tolist(),
              "held_out": bool(data.held_out[k]), "frames": 1}
             for k, f in enumerate(data.filenames)]
    steps.append({"kind": MASK_STEP, "file": "mask.png", "frames": 1})
    if data.normals_gt is not None:
        steps.append({"kind": TRUTH_STEP, "file": "Normal_gt.mat", "frames": 1,
                      "use": "scoring only"})
    if not isinstance(store, Store):
        store = Store.open(store, create=True)
    try:
        info = store.session(name)
    except SessionNotFound:
        info = store.create_session(name, plan=plan, plan_hash=plan_hash, steps=steps,
                                    plan_path=str(d.resolve()), operator=operator, object=data.name,
                                    notes=f"imported from {d.resolve()} ({FORMAT} layout)")
    else:
        if info.state == "done" or info.plan_hash != plan_hash:
            raise SessionExists(f"a session named {name!r} already exists in {store.root}; choose "
                                "another --session name")
    try:
        with store.writer(name):
            stored = {f.step: f.id for f in store.frames(info.id)}
            ids = []
            for i, s in enumerate(steps):
                if i in stored:   # an interrupted import of the same files: kept
                    ids.append(stored[i])
                    continue
                fid, _ = store.add_frame(info.id, i, 0, 0, data=(d / s["file"]).read_bytes(),
                                         filename=s["file"], format=Path(s["file"]).suffix[1:],
                                         exposure_requested_s=None, exposure_s=None,
                                         metadata={"imported_from": str(d.resolve() / s["file"])},
                                         completes_step=True)
                ids.append(fid)
            K = len(data.filenames)
            given = {r.kind for r in store.results(info.id, "calibration")}   # stored before a cut
            if "lights_directional" not in given:
                store.add_calibration(info.id, "lights_directional", result={
                    "directions": data.light_directions.tolist(),
                    "intensities": data.light_intensities.tolist(),
                    "frame": plan["imported"]["frame"],
                    "source": "given with the set (light_directions.txt, light_intensities.txt)"},
                    params={"format": FORMAT}, input_frames=ids[:K])
            if "camera_orthographic" not in given:
                store.add_calibration(info.id, "camera_orthographic", result={
                    "view_direction": data.view_direction.tolist(), "image_size_px": [W, H],
                    "source": "given with the set (DiLiGenT: orthographic, view along the optical axis)"},
                    params={"format": FORMAT})
            store.set_state(info.id, "done", [Event(
                EventKind.NOTE, name, f"imported {K} images from {d.resolve()} ({FORMAT} layout)",
                data={"source": str(d.resolve()), "lights": K,
                      "held_out": int(data.held_out.sum()),
                      "ground_truth": data.normals_gt is not None})])
    except BaseException:
        store.set_state(info.id, "paused")   # the same command continues it
        raise
    return name


def read_imported_session(store: Store, session: str) -> MultiLightSet:
    """The :class:`MultiLightSet` of a session written by :func:`import_diligent`, decoded from
    the stored frames (the files' own bytes). ValueError if the session was not imported."""
    info = store.session(session)
    meta = info.plan.get("imported") if isinstance(info.plan, dict) else None
    if not meta or meta.get("format") != FORMAT:
        raise ValueError(f"session {session!r} was not imported from a {FORMAT} set")
    steps = {s.index: s.spec for s in store.steps(info.id)}
    frames = {f.step: f for f in store.frames(info.id)}
    missing = [i for i in steps if i not in frames]
    if missing:
        raise ValueError(f"session {session!r}: steps {missing[:5]} have no stored frame "
                         "(an interrupted import: import again)")

    def decode(i):
        buf = np.frombuffer(store.read_object(frames[i].sha256), np.uint8)
        return cv2.imdecode(buf, cv2.IMREAD_UNCHANGED)

    lights = [i for i, s in steps.items() if s["kind"] == LIGHT_STEP]
    images = np.stack([decode(i)[..., ::-1] for i in lights])
    mask_step = next(i for i, s in steps.items() if s["kind"] == MASK_STEP)
    m = decode(mask_step)
    mask = (m[..., 0] if m.ndim == 3 else m) > 0
    normals = None
    truth = [i for i, s in steps.items() if s["kind"] == TRUTH_STEP]
    if truth:
        mat = scipy.io.loadmat(io.BytesIO(store.read_object(frames[truth[0]].sha256)))
        normals = np.where(mask[..., None], mat["Normal_gt"] * _FLIP, 0.0)
    return MultiLightSet(name=meta["object"], images=images,
                         full_scale=float(np.iinfo(images.dtype).max),
                         light_directions=np.array([steps[i]["light_direction"] for i in lights]),
                         light_intensities=np.array([steps[i]["light_intensity"] for i in lights]),
                         mask=mask, normals_gt=normals,
                         filenames=tuple(steps[i]["file"] for i in lights),
                         held_out=np.array([steps[i]["held_out"] for i in lights]))
