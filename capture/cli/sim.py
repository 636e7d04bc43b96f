"""``gonio sim``: look at the simulated lab's picture.

- ``gonio sim render --object bunny --turntable 30 --light-az 45 --light-el 30 --polarizer 0
  --exposure 0.01 --out DIR`` renders any scene and rig state through the simulated camera and
  writes the camera's DNG plus a PNG preview (the DNG developed with its own white balance,
  sRGB-encoded, sensor white = display white); ``--truth`` adds the noise-free ground truth.
"""
from __future__ import annotations

import io
import json
import math
import time
from pathlib import Path
from typing import Optional

import typer

from ..outputs import OutputError, check_out_folder, safe_stem, write_atomically

#: largest rendered side, pixels (64 MP frames; beyond that a typo runs out of memory)
MAX_SIDE_PX = 8192
#: rays per pixel side at most (64 rays a pixel)
MAX_SUPERSAMPLE = 8

app = typer.Typer(name="sim", help="Render the simulated lab: scenes, targets and the camera's raw frames.",
                  no_args_is_help=True)

#: sims.world.CAPTURE_KINDS, restated so that --help does not import the renderer (tests/sims/test_world.py)
SCENES = ("object", "checkerboard", "handheld_board", "charuco", "chrome", "spheres", "gray_card", "mirror_probe",
          "passive", "passive_sphere", "dark", "flat")


def _fail(message: str, code: int = 2) -> typer.Exit:
    typer.secho(f"error: {message}", err=True, fg=typer.colors.RED)
    return typer.Exit(code)


def preview_png(dng: bytes):
    """Develop DNG bytes for display: demosaic with the camera's white balance, no auto-brightening,
    sensor white level -> display white, sRGB transfer curve -> (H, W, 3) uint8 RGB."""
    import numpy as np
    import rawpy

    with rawpy.imread(io.BytesIO(dng)) as r:
        lin = r.postprocess(use_camera_wb=True, output_color=rawpy.ColorSpace.raw, gamma=(1, 1),
                            no_auto_bright=True, output_bps=16,
                            demosaic_algorithm=rawpy.DemosaicAlgorithm.LINEAR)
    x = np.clip(lin.astype(np.float32) / 65535.0, 0.0, 1.0)
    srgb = np.where(x <= 0.0031308, 12.92 * x, 1.055 * np.power(x, 1 / 2.4) - 0.055)
    return np.rint(srgb * 255).astype(np.uint8)


# one paragraph per string: rich help keeps line breaks as written
_RENDER_HELP = "\n\n".join([
    "Render one frame of the simulated rig and write NAME.dng and NAME.png into --out.",
    "The frame is what the simulated camera returns for that rig state: the scene (the object on "
    "the turntable, or a calibration target with --scene) rendered from the rig's fixed camera "
    "(lens distortion included) under the lamp on the light arm, exposed on the simulated sensor "
    "(shot and read noise, dark current, vignetting, Bayer mosaic, clipping at the white level) "
    "and written as the camera's raw DNG. The PNG is that DNG developed for viewing: demosaiced "
    "with the camera's white balance, linear, sensor white = display white, sRGB-encoded. Nothing "
    "is auto-brightened, so an under-exposed frame looks dark (raise --exposure or --iso).",
    "Frames: world = turntable frame (+z up the axis, mm). The camera stands at azimuth 0 (on +x) "
    "looking down at the platter: --light-az 0 lights the object from the camera's side, positive "
    "azimuths move the lamp to the camera's right, and --turntable turns the object "
    "counter-clockwise seen from above.",
    "Examples: gonio sim render --out out --object bunny --turntable 180 --light-az 30 | "
    "gonio sim render --out out --scene charuco --turntable 20 | "
    "gonio sim render --out out --polarizer 90 --truth",
    "Exit codes: 0 written; 2 bad arguments (the message names the option).",
])


@app.command(help=_RENDER_HELP)
def render(
    out: str = typer.Option(..., "--out", help="Folder for the DNG and PNG (created if needed)."),
    obj: str = typer.Option("sphere", "--object", help="On the turntable: sphere, hemisphere, multi, bunny or none."),
    scene: str = typer.Option("object", "--scene", help=f"Capture kind: {', '.join(SCENES)}."),
    turntable: float = typer.Option(0.0, "--turntable", help="Turntable angle, degrees."),
    light_az: float = typer.Option(45.0, "--light-az", help="Light azimuth from world +x towards +y, degrees."),
    light_el: float = typer.Option(30.0, "--light-el", help="Light elevation above the platter plane, degrees."),
    light_radius: float = typer.Option(500.0, "--light-radius", help="Light arm radius about the origin, mm."),
    polarizer: Optional[float] = typer.Option(None, "--polarizer", help="Analyser angle on the lens, degrees (omit: none)."),
    exposure: float = typer.Option(0.01, "--exposure", help="Exposure time, seconds."),
    iso: float = typer.Option(100.0, "--iso", help="ISO."),
    fnumber: float = typer.Option(8.0, "--fnumber", help="Aperture f-number."),
    width: int = typer.Option(1200, "--width", help="Image width, pixels."),
    height: int = typer.Option(800, "--height", help="Image height, pixels."),
    supersample: Optional[int] = typer.Option(None, "--supersample",
                                              help="Rays per pixel side (default: 2 for boards, else 1)."),
    seed: int = typer.Option(0, "--seed", help="Seed of the sensor noise."),
    truth: bool = typer.Option(False, "--truth", help="Also write NAME_truth.npz (radiance, buffers) and NAME.json."),
    name: Optional[str] = typer.Option(None, "--name", help="File stem (default: from the scene and state)."),
) -> None:
    """Render one frame of the simulated rig and write NAME.dng and NAME.png into --out."""
    import cv2
    import numpy as np

    from sims.objects import OBJECTS
    from sims.ptp_sim import FNUMBER_VALUES, ISO_VALUES
    from ..plan import MAX_EXPOSURE_S, MIN_EXPOSURE_S
    from sims.world import SimWorld, default_camera, light_position

    if scene not in SCENES:
        raise _fail(f"--scene must be one of {', '.join(SCENES)}, got {scene!r}")
    if obj not in OBJECTS + ("none",):
        raise _fail(f"--object must be one of {', '.join(OBJECTS + ('none',))}, got {obj!r}")
    if width < 16 or height < 16 or width % 2 or height % 2 or max(width, height) > MAX_SIDE_PX:
        raise _fail(f"--width and --height must be even and in 16..{MAX_SIDE_PX} (a Bayer mosaic), "
                    f"got {width} x {height}")
    for option, value in (("--turntable", turntable), ("--light-az", light_az), ("--light-el", light_el),
                          ("--polarizer", polarizer)):
        if value is not None and not math.isfinite(value):
            raise _fail(f"{option} must be a finite number of degrees, got {value!r}")
    if name is not None and not safe_stem(name):   # a file stem, never a path: nothing outside --out
        raise _fail(f"--name {name!r}: use 1-100 ASCII letters, digits, '_', '.' or '-', starting with a "
                    "letter, digit or '_' (a file stem, not a path)")
    try:
        folder = check_out_folder(out)
    except OutputError as exc:
        raise _fail(str(exc)) from None
    if not 0 < light_radius < math.inf:  # also catches NaN
        raise _fail(f"--light-radius must be > 0, got {light_radius!r}")
    for option, value, (low, high) in (("--exposure", exposure, (MIN_EXPOSURE_S, MAX_EXPOSURE_S)),
                                       ("--iso", iso, (min(ISO_VALUES), max(ISO_VALUES))),
                                       ("--fnumber", fnumber, (min(FNUMBER_VALUES) / 100, max(FNUMBER_VALUES) / 100))):
        if not low <= value <= high:  # the simulated camera's range (and plans' exposures); false for NaN
            raise _fail(f"{option} must be in {low:g}..{high:g}, got {value!r}")
    if not -90 <= light_el <= 90:
        raise _fail(f"--light-el must be in -90..90 degrees, got {light_el!r}")
    if supersample is not None and not 1 <= supersample <= MAX_SUPERSAMPLE:
        raise _fail(f"--supersample must be in 1..{MAX_SUPERSAMPLE} rays per pixel side, got {supersample}")
    if seed < 0:
        raise _fail(f"--seed must be >= 0, got {seed}")
    # every option is checked above: an error from here on is a bug, and keeps its traceback
    extra = {} if supersample is None else {"supersample": supersample}
    world = SimWorld.for_capture(scene, None if obj == "none" else obj,
                                 camera=default_camera(width, height), seed=seed, **extra)
    state = {"turntable_angle_deg": turntable, "exposure_s": exposure, "iso": iso, "fnumber": fnumber,
             "light_position_mm": tuple(light_position(light_az, light_el, radius_mm=light_radius)),
             "polarizer_angle_deg": polarizer}
    t0 = time.perf_counter()
    dng = world.frame_source(state)
    seconds = time.perf_counter() - t0
    stem = name or (f"{obj if scene == 'object' else scene}_tt{turntable:g}_az{light_az:g}_el{light_el:g}"
                    f"_pol{'none' if polarizer is None else f'{polarizer:g}'}_e{exposure:g}")
    folder.mkdir(parents=True, exist_ok=True)
    dng_path, png_path = folder / f"{stem}.dng", folder / f"{stem}.png"
    rgb = preview_png(dng)
    files = {dng_path: dng, png_path: cv2.imencode(".png", rgb[..., ::-1])[1].tobytes()}
    if truth:
        files.update(_truth_files(world, state, folder, stem))
    try:   # each whole or not at all (a full disk, a read-only folder)
        for path, data in files.items():
            write_atomically(path, data)
    except OSError as exc:
        raise _fail(f"cannot write {exc.filename}: {exc.strerror or exc}") from None
    saturated = float(np.mean(rgb.max(axis=2) == 255))
    typer.echo(f"{dng_path}\n{png_path}\n{width} x {height}, rendered and exposed in {seconds:.2f} s, "
               f"{100 * saturated:.1f} % of pixels at sensor white")
    if truth:
        typer.echo(f"{folder / f'{stem}_truth.npz'}\n{folder / f'{stem}.json'}")


def _truth_files(world, state: dict, out: Path, stem: str) -> dict[Path, bytes]:
    """``NAME_truth.npz`` (radiance, buffers) and ``NAME.json`` (state, camera, light, pose), as bytes."""
    import numpy as np
    gt = world.ground_truth(state)
    b = gt.buffers
    npz = io.BytesIO()
    np.savez_compressed(npz, radiance=gt.radiance, diffuse=gt.diffuse,
                        specular=gt.specular, mask=b.mask, normal=b.normal,
                        position=b.position, depth=b.depth, uv=b.uv, surface_index=b.surface_index,
                        face_index=b.face_index, expected_dn=gt.expected.mean_dn,
                        sigma_dn=gt.expected.sigma_dn, saturated=gt.expected.saturated)
    meta = {"state": {k: v for k, v in vars(gt.state).items()},
            "camera": {"K": gt.camera.K.tolist(), "dist": gt.camera.dist.tolist(), "R": gt.camera.R.tolist(),
                       "t": gt.camera.t.tolist(), "width": gt.camera.width, "height": gt.camera.height},
            "light_position_mm": gt.light_position_mm.tolist(), "object_pose": gt.object_pose.tolist(),
            "objects": [o.name for o in gt.scene.objects]}
    return {out / f"{stem}_truth.npz": npz.getvalue(), out / f"{stem}.json": json.dumps(meta, indent=2)}
