"""The light-probe calibration against the simulated room: ``python benchmarks/probe.py [--sizes 320x240,640x480]``.

For each camera resolution, the demo lab's mirror-probe frame (``capture.pipeline.demo_lab.DemoLab``:
the 25.4 mm chrome ball under Grace Cathedral) as the sensor's noise-free Bayer mosaic (its colour
filters, channel responses and vignetting), calibrated as ``gonio calibrate``'s probe stage does,
against the true map the lab renders with. Prints

- the circle: the Hough start and the fitted limb (``calibration.spheres.find_mirror_sphere``)
  against the ball's true image circle (radius px and %, centre px);
- the map: per channel, the energy ratio (map over truth, fully seen texels) and the relative
  RMS irradiance error of 300 random normals (32-row maps), for the bilinear demosaic the
  session's images use and for the probe's smooth-hue demosaic
  (``calibration.raw.demosaic_smooth_hue``), with the found circle; and, as the floor, the
  renderer's RGB (no mosaic) with the true circle.

A 320 x 240 frame renders in ~50 s on a loaded 2-core machine (the ball is pixel-integrated at
320 rays across), 640 x 480 in about as long.
"""
from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

sys.path = [p for p in sys.path if Path(p or ".").resolve() != Path(__file__).resolve().parent]
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import cv2  # noqa: E402
import numpy as np  # noqa: E402

from calibration.probe import mirror_sphere_to_latlong  # noqa: E402
from calibration.raw import demosaic_bilinear, demosaic_smooth_hue  # noqa: E402
from calibration.spheres import _tone, find_mirror_sphere  # noqa: E402
from capture.pipeline.demo_lab import DemoLab  # noqa: E402
from reconstruct.envmap import EnvironmentMap  # noqa: E402
from sims.targets import CHROME_REFLECTANCE, environment  # noqa: E402
from sims.world import sphere_target  # noqa: E402

MAP_HEIGHT = 128  # the calibrate stage's smallest map


def map_errors(env_map, weight, truth: EnvironmentMap, response) -> tuple[np.ndarray, np.ndarray]:
    """(energy ratio (3,), irradiance rel. RMS (3,)) of a probe map (camera DN/s, with the ball's
    reflectance) against the true environment (renderer radiance)."""
    radiance = env_map / CHROME_REFLECTANCE / response
    good = weight >= 1
    want = truth.resized(MAP_HEIGHT).image
    ratio = radiance[good].sum(axis=0) / want[good].sum(axis=0)
    normals = np.random.default_rng(1).normal(size=(300, 3))
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    have = EnvironmentMap(radiance).resized(32).irradiance(normals)
    ref = truth.resized(32).irradiance(normals)
    return ratio, np.sqrt(np.mean((have - ref) ** 2, axis=0) / np.mean(ref ** 2, axis=0))


def run(width: int, height: int, truth: EnvironmentMap) -> None:
    lab = DemoLab(width, height)
    world, cam = lab.worlds["mirror_probe"], lab.camera
    t0 = time.perf_counter()
    rad = world.radiance({"turntable_deg": 0.0})
    render_s = time.perf_counter() - t0
    sensor = world.sensor
    K, t = cam.K, 0.004
    optics = dict(fnumber=8.0, focal_px=float(np.sqrt(K[0, 0] * K[1, 1])), principal_point=(K[0, 2], K[1, 2]))
    mosaic = (sensor.expected_raw(rad, t, **optics).mean_dn - sensor.black_level) / t
    channels = sensor.cfa_channels(height, width)
    response = lab.truth().sensor_dn_per_radiance  # DN/s per unit radiance at the image centre
    ball = sphere_target("chrome")
    centre = ball.points_world(0.0)[0]
    d = np.linalg.norm(cam.R @ centre + cam.t)
    true_r = cam.K[0, 0] * ball.spec.radius_mm / np.sqrt(d * d - ball.spec.radius_mm ** 2)
    true_c = cam.project(centre[None])[0]
    print(f"\n== {width} x {height}: render {render_s:.0f} s; the ball's true circle ({true_c[0]:.2f}, "
          f"{true_c[1]:.2f}) px, r {true_r:.2f} px ==")
    images = {"bilinear": demosaic_bilinear(mosaic, channels), "smooth hue": demosaic_smooth_hue(mosaic, channels)}
    g8 = (np.sqrt(_tone(images["smooth hue"])) * 255).astype(np.uint8)
    h, w = g8.shape
    hough = cv2.HoughCircles(g8, cv2.HOUGH_GRADIENT_ALT, dp=1.0, minDist=min(h, w) / 4, param1=100,
                             param2=0.75, minRadius=5, maxRadius=min(h, w) // 2).reshape(-1, 3)[0]
    print(f"{'circle':34s} {'radius px':>10s} {'radius %':>9s} {'centre px':>10s}")
    print(f"{'Hough start':34s} {hough[2] - true_r:+10.2f} {100 * (hough[2] / true_r - 1):+9.2f} "
          f"{np.linalg.norm(hough[:2] - true_c):10.2f}")
    found = {}
    for name, img in images.items():
        sp = found[name] = find_mirror_sphere(img, reflectance=CHROME_REFLECTANCE)
        print(f"{'limb fit, ' + name:34s} {sp.radius_px - true_r:+10.2f} {100 * (sp.radius_px / true_r - 1):+9.2f} "
              f"{np.linalg.norm(sp.center_px - true_c):10.2f}")
    print(f"{'map (R, G, B)':34s} {'energy ratio':>22s} {'irradiance rel. RMS':>24s}")
    rows = [("renderer RGB, true circle (floor)", rad * response, true_c, true_r)]
    rows += [(f"{name}, found circle", img, found[name].center_px, found[name].radius_px)
             for name, img in images.items()]
    rows.append(("bilinear, true circle", images["bilinear"], true_c, true_r))
    for label, img, c, r in rows:
        p = mirror_sphere_to_latlong(img, c, r, cam.R, height=MAP_HEIGHT)
        ratio, rel = map_errors(p.env, p.weight, truth, response)
        print(f"{label:34s} {np.array2string(ratio, precision=3):>22s} {np.array2string(rel, precision=3):>24s}")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sizes", default="320x240,640x480", help="camera resolutions, WxH, comma-separated")
    args = ap.parse_args()
    truth = environment("grace")
    for size in args.sizes.split(","):
        run(*(int(v) for v in size.split("x")), truth)


if __name__ == "__main__":
    main()
