"""Auto-exposure from metering shots (raw histogram), alone and in the runner on the sim lab."""
from __future__ import annotations

import numpy as np
import pytest

from capture.events import EventKind
from capture.metering import MeteringError, meter, raw_signal
from capture.plan import Plan
from capture.rigs import open_rig
from capture.runner import Runner, create_session
from capture.store import Store
from capture_fakes import tolerant_sim_config
from sims.dng import write_dng
from sims.ptp_sim import placeholder_frame

LIMITS = (1e-4, 30.0)
#: the synthetic camera: white level and a different black level per 2x2 tile position (DN)
WHITE = 16000
BLACKS = (256, 1800, 2400, 4000)
T0 = 0.01
#: the scene as the fraction of each photosite's usable range it reaches at T0 (noise-free)
SCENE = np.tile(np.linspace(0.02, 0.5, 96, dtype=np.float64), (64, 1))


def _camera():
    """Noise-free linear camera: DN = black_c + SCENE * t / T0 * (white - black_c), clipped."""
    shots = []
    black = np.tile(np.reshape(BLACKS, (2, 2)), (32, 48))

    def capture(t: float) -> bytes:
        shots.append(t)
        dn = black + np.minimum(SCENE * t / T0, 1.0) * (WHITE - black)
        return write_dng(np.rint(dn).astype(np.uint16), black_level=BLACKS, white_level=WHITE, exposure_s=t)
    return capture, shots


def _expected_exposure(highlight: float, percentile: float = 99.5) -> float:
    """Closed form: the signal is linear in time, so the percentile reaches ``highlight`` at
    T0 * highlight / percentile(SCENE)."""
    return T0 * highlight / float(np.percentile(SCENE, percentile))


def test_raw_signal_uses_each_channels_black_level():
    capture, _ = _camera()
    # one DN of rounding in a usable range of >= 12000 DN
    np.testing.assert_allclose(raw_signal(capture(T0)), SCENE, atol=1e-4)


def test_metered_exposure_puts_highlights_at_target():
    capture, shots = _camera()
    m = meter(capture, T0, limits_s=LIMITS, highlight=0.8)
    assert len(shots) == 1  # an unclipped first shot is enough (raw is linear in time)
    assert m.exposure_s == pytest.approx(_expected_exposure(0.8), rel=1e-3)


def test_clipped_start_is_shortened_then_metered():
    capture, shots = _camera()
    m = meter(capture, 1.0, limits_s=LIMITS, highlight=0.6)
    assert shots[0] == 1.0 and shots[1] == pytest.approx(1.0 / 16)
    assert m.shots[0]["saturated_fraction"] > 0.5
    assert m.exposure_s == pytest.approx(_expected_exposure(0.6), rel=1e-3)


def test_dark_start_is_lengthened():
    capture, shots = _camera()
    m = meter(capture, 1e-4, limits_s=LIMITS)
    assert len(shots) == 2 and shots[1] == pytest.approx(16e-4)
    assert m.exposure_s == pytest.approx(_expected_exposure(0.8), rel=1e-3)


def test_too_dark_within_limits_is_an_error():
    capture, _ = _camera()
    with pytest.raises(MeteringError, match="too dark to meter even at the longest exposure 0.0001 s"):
        meter(capture, 1e-5, limits_s=(1e-5, 1e-4))


def test_non_raw_bytes_are_an_error():
    with pytest.raises(MeteringError, match="not a raw file"):
        meter(lambda t: b"JPEG?", 0.01, limits_s=LIMITS)


def test_runner_meters_once_and_resume_reuses_it(tmp_path):
    plan = Plan.from_dict({"turntable": {"angles_deg": [0, 90, 180]},
                           "exposure": {"base_s": 0.002, "stops": [-1, 0, 1], "auto": True,
                                        "highlight": 0.5},
                           "calibration": [{"kind": "dark", "frames": 1}]})
    with open_rig(tolerant_sim_config(), fast=True, home=True, frame_source=placeholder_frame) as opened, \
            Store(tmp_path) as store:
        info = create_session(store, plan, opened.rig, name="s", reserve_bytes=0)
        events = []
        r = Runner(opened.rig, store, "s", reserve_bytes=0)
        r.bus.subscribe(events.append)
        r.bus.subscribe(lambda e: e.kind == EventKind.STEP_DONE and e.step == 1 and r.request_pause())
        assert r.run() == "paused"
        assert r.run() == "done"
        [metering] = [x for x in store.results(info.id) if x.kind == "metering"]
        t = metering.result["exposure_s"]
        assert 0.002 < t < 0.05 and metering.artifacts  # the metering shots are kept
        metered = [e for e in events if e.kind == EventKind.METERED]
        assert len(metered) == 2 and "stored metering" in metered[1].message
        frames = store.frames(info.id)
        assert len(frames) == 3 + 3 * 3  # dark bracket + 3 poses x 3
        for f in frames:  # dark frames and measurements follow the same metered bracket
            assert f.exposure_requested_s == pytest.approx(t * 2.0 ** (f.bracket_index - 1))
        assert store.verify("s").ok
