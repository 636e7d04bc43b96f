"""The one HDR path for stored frames (capture.pipeline.images): dark lookup, exposure fallback,
stored darks found by their recorded exposure."""
from __future__ import annotations

import io

import numpy as np
import pytest

from capture.pipeline.images import FrameDataError, SessionImages, dark_artifact_name
from capture.plan import Step
from capture.store import Store
from sims.dng import write_dng

BLACK, WHITE = 64, 4095
H, W = 32, 48


def _session(tmp_path, exposures, *, recorded=None):
    """A store with one step whose frames see radiance ``L`` (DN/s) plus a fixed dark pattern.
    ``recorded[k]`` is the exposure stored for frame k (None: only the requested one)."""
    rng = np.random.default_rng(3)
    radiance = rng.uniform(2_000, 20_000, (H, W))
    pattern = rng.uniform(10, 40, (H, W))  # >= 10 DN: a missed dark shows
    store = Store(tmp_path / "st", durable=False)
    step = Step(0, "measure", "object", None, None, None, tuple(exposures))
    sid = store.create_session("s", plan={}, plan_hash="h", steps=[step.to_dict()]).id
    for k, t in enumerate(exposures):
        raw = np.round(BLACK + pattern + radiance * t).astype(np.uint16)
        t_rec = t if recorded is None else recorded[k]
        store.add_frame(sid, 0, k, 0, data=write_dng(raw, black_level=BLACK, white_level=WHITE),
                        filename=f"{k}.dng", format="dng", exposure_requested_s=t, exposure_s=t_rec)
    return store, radiance, BLACK + pattern


def _green(img):
    return img[0::2, 1::2, 1]  # RGGB: a green photosite's own value survives the demosaic


def test_merge_subtracts_the_dark_of_each_exposure_within_one_percent(tmp_path):
    store, radiance, dark = _session(tmp_path, [0.01, 0.04])
    images = SessionImages(store, "s")
    images.darks = {0.01 * 1.009: dark, 0.04 * 0.992: dark}   # both within the 1 % tolerance
    im = images.merge(0)
    assert im.dark_subtracted == 2 and im.exposures_s == [0.01, 0.04]
    # rounding to integer DN is the only error left: at most 0.5 DN / 10 ms = 50 DN/s, while a
    # missed dark would add 10-40 DN / 40 ms >= 250 DN/s
    np.testing.assert_allclose(_green(im.radiance), radiance[0::2, 1::2], atol=50)
    store.close()


def test_a_dark_two_percent_off_is_not_used(tmp_path):
    store, radiance, dark = _session(tmp_path, [0.01])
    images = SessionImages(store, "s")
    images.darks = {0.0102: dark}
    im = images.merge(0)
    assert im.dark_subtracted == 0
    # black level only: the dark pattern (10-40 DN) stays in, divided by 10 ms (+- 50 DN/s rounding)
    excess = _green(im.radiance) - radiance[0::2, 1::2]
    np.testing.assert_allclose(excess, (dark - BLACK)[0::2, 1::2] / 0.01, atol=60)
    store.close()


def test_the_requested_exposure_stands_in_for_a_missing_read_back(tmp_path):
    store, radiance, _ = _session(tmp_path, [0.02], recorded=[None])
    im = SessionImages(store, "s").merge(0)
    assert im.exposures_s == [0.02]
    store.close()


def test_a_frame_without_any_exposure_time_is_named(tmp_path):
    store, _, _ = _session(tmp_path, [0.02])
    sid = store.session("s").id
    store.add_frame(sid, 0, 1, 0, data=b"x", filename="bad.dng", format="dng",
                    exposure_requested_s=None, exposure_s=None)
    with pytest.raises(FrameDataError, match=r"frame \d+ \(step 0\) has no exposure time"):
        SessionImages(store, "s").merge(0)
    store.close()


def test_stored_darks_are_keyed_by_their_recorded_exposure(tmp_path):
    # 1/3 s: the artifact name holds '0.333333', the record holds the exposure itself
    store, _, dark = _session(tmp_path, [1 / 3])
    t = 1 / 3
    buf = io.BytesIO()
    np.save(buf, dark)
    sid = store.session("s").id
    store.add_calibration(sid, "dark", result={"darks": [{"exposure_s": t}]},
                          artifacts={dark_artifact_name(t): buf.getvalue()})
    [row] = store.results(sid, "calibration")
    images = SessionImages(store, "s")
    images.use_stored_darks([t], row.artifacts, 2.5)
    assert list(images.darks) == [t] and images.read_noise_dn == 2.5
    assert images.merge(0).dark_subtracted == 1
    store.close()
