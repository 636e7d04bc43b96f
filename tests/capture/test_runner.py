"""Runner against in-process fake devices: order, durability, retries, faults, pause/abort, disk."""
from __future__ import annotations

import threading

import pytest

from capture.events import EventKind
from capture.plan import Plan
from capture.runner import (RetryPolicy, Runner, RunnerError, check_plan_unchanged, create_session,
                            estimate_remaining)
from capture.store import Store
from capture_fakes import SMALL_PLAN, make_rig

FAST_RETRY = RetryPolicy(attempts=3, base_delay_s=0.001, max_delay_s=0.004)
PLANNED_STEPS = 12            # 3 turntable x 2 light x 2 polarizer
PLANNED_FRAMES = 12 * 2       # bracket of 2


@pytest.fixture
def setup(tmp_path):
    store = Store(tmp_path / "store")
    rig = make_rig()
    info = create_session(store, Plan.from_dict(SMALL_PLAN), rig, name="s", reserve_bytes=0)
    yield store, rig, info
    store.close()


def _runner(store, rig, events=None, **kw):
    r = Runner(rig, store, "s", retry=FAST_RETRY, reserve_bytes=0, **kw)
    if events is not None:
        r.bus.subscribe(events.append)
    return r


def _assert_complete(store, info):
    frames = store.frames(info.id)
    keys = [(f.step, f.bracket_index, f.repeat) for f in frames]
    assert len(frames) == PLANNED_FRAMES and len(set(keys)) == PLANNED_FRAMES
    assert sorted(keys) == [(s, b, 0) for s in range(PLANNED_STEPS) for b in range(2)]
    assert store.verify("s").ok
    assert store.session("s").state == "done"


def test_frame_progress_reaches_the_planned_frames_in_order(setup):
    """``on_frame_stored`` (what ``gonio demo``'s capture bar reads) counts 1..N of N frames."""
    store, rig, info = setup
    seen = []
    runner = _runner(store, rig)
    runner.on_frame_stored(lambda done, total: seen.append((done, total)))
    assert runner.run() == "done"
    assert seen == [(k, PLANNED_FRAMES) for k in range(1, PLANNED_FRAMES + 1)]


def test_runs_every_step_with_readbacks_and_events(setup):
    store, rig, info = setup
    events = []
    assert _runner(store, rig, events).run() == "done"
    _assert_complete(store, info)
    kinds = [e.kind for e in events]
    assert kinds[0] == EventKind.SESSION_STARTED and kinds[-1] == EventKind.DONE
    assert kinds.count(EventKind.STEP_STARTED) == PLANNED_STEPS
    assert kinds.count(EventKind.MOVED) == PLANNED_STEPS
    assert kinds.count(EventKind.FRAME_STORED) == PLANNED_FRAMES
    last = [e for e in events if e.kind == EventKind.FRAME_STORED][-1]
    assert last.data["frames_done"] == PLANNED_FRAMES and last.data["steps_done"] == PLANNED_STEPS
    # read-backs per frame equal the planned pose (fake devices land exactly)
    steps = {s.index: s.step for s in store.steps(info.id)}
    for f in store.frames(info.id):
        st = steps[f.step]
        assert f.positions["turntable_deg"] == st.turntable_deg
        assert f.positions["polarizer_deg"] == st.polarizer_deg
        assert f.exposure_requested_s == pytest.approx(st.exposures_s[f.bracket_index])
        assert f.exposure_s == pytest.approx(f.exposure_requested_s)
    # moves of different devices were issued per step, only where the plan says
    assert len(rig.turntable.moves) == PLANNED_STEPS
    # events are persisted in the store as well
    stored = [e["kind"] for e in store.events(info.id)]
    assert stored.count("frame_stored") == PLANNED_FRAMES and stored[-1] == "done"
    assert store.rig_snapshots(info.id)[0]["describe"]["turntable"]["driver"] == "fake"


def test_moves_run_concurrently(tmp_path):
    # each step moves both axes; their moves meet at a barrier, which a runner that waited for
    # one move before starting the next could never pass (no wall-clock margins)
    store = Store(tmp_path)
    rig = make_rig(move_s=0.01)
    rig.polarizer.move_s = 0.01
    barrier = threading.Barrier(2, timeout=30)
    rig.turntable.rendezvous = rig.polarizer.rendezvous = barrier
    plan = Plan.from_dict({"turntable": {"angles_deg": [10, 20]}, "polarizer": {"angles_deg": [10, 20]},
                           "exposure": {"stops": [0]}})
    create_session(store, plan, rig, name="s", reserve_bytes=0)
    assert _runner(store, rig).run() == "done"
    assert not barrier.broken
    assert len(rig.turntable.moves) == len(rig.polarizer.moves) == 4  # 2 x 2 grid, both per step
    store.close()


def test_retryable_faults_are_retried(setup):
    store, rig, info = setup
    rig.camera.inject("timeout", 2)
    rig.turntable.inject("busy", 1)
    rig.positioner.inject("garble", 1)
    events = []
    assert _runner(store, rig, events).run() == "done"
    retries = [e for e in events if e.kind == EventKind.RETRY]
    assert sorted(e.device for e in retries) == ["camera", "camera", "positioner", "turntable"]
    assert retries[0].data["delay_s"] == pytest.approx(0.001)
    _assert_complete(store, info)


def test_exhausted_retries_pause_then_resume_completes(setup):
    store, rig, info = setup
    rig.camera.inject("timeout", 3)  # = attempts
    events = []
    assert _runner(store, rig, events).run() == "paused"
    assert store.session("s").state == "paused"
    fault = [e for e in store.events(info.id) if e["kind"] == "fault"]
    assert fault and fault[0]["device"] == "camera" and fault[0]["data"]["attempts"] == 3
    assert "resume" in [e for e in events if e.kind == EventKind.PAUSED][-1].message
    assert rig.turntable.stops >= 1  # the rig was stopped on the fault
    assert _runner(store, rig).run() == "done"
    _assert_complete(store, info)


def test_disconnect_pauses_at_once_and_resume_reconnects(setup):
    store, rig, info = setup
    events = []
    r = _runner(store, rig, events)

    def pull_cable(e):
        if e.kind == EventKind.FRAME_STORED and e.data["frames_done"] == 7:
            rig.positioner.inject("disconnect")
    r.bus.subscribe(pull_cable)
    assert r.run() == "paused"
    assert not [e for e in events if e.kind == EventKind.RETRY]
    [fault] = [e for e in events if e.kind == EventKind.FAULT]
    assert fault.device == "positioner" and fault.data["error"] == "Disconnected"
    assert not rig.positioner.connected
    connects = rig.positioner.connects
    assert r.run() == "done"  # the same runner reconnects the dropped device
    assert rig.positioner.connects == connects + 1
    _assert_complete(store, info)
    assert [e.kind for e in events].count(EventKind.RESUMED) == 1


def test_pause_request_between_steps_and_resume(setup):
    store, rig, info = setup
    events = []
    r = _runner(store, rig, events)
    r.bus.subscribe(lambda e: e.kind == EventKind.STEP_STARTED and e.step == 4 and r.request_pause())
    assert r.run() == "paused"
    assert store.progress(info.id).steps_done == 5  # the current step is finished first
    assert _runner(store, rig).run() == "done"
    _assert_complete(store, info)


def test_pause_now_interrupts_step_and_redo_replaces_frames(setup):
    store, rig, info = setup
    r = _runner(store, rig)
    r.bus.subscribe(lambda e: e.kind == EventKind.FRAME_STORED and e.data["frames_done"] == 9
                    and r.request_pause(now=True))
    assert r.run() == "paused"
    p = store.progress(info.id)
    assert (p.steps_done, p.frames_stored) == (4, 9)  # step 4 half done
    assert _runner(store, rig).run() == "done"
    _assert_complete(store, info)


def test_estimate_remaining_counts_steps_not_done_with_the_stored_frame_size(setup):
    store, rig, info = setup
    rig.camera.describe = lambda: {"driver": "fake"}  # no size from the camera
    assert estimate_remaining(store, "s", rig).frame_bytes_assumed
    r = _runner(store, rig)
    r.bus.subscribe(lambda e: e.kind == EventKind.STEP_DONE and e.step == 4 and r.request_pause())
    assert r.run() == "paused"
    est = estimate_remaining(store, info, rig)
    left = PLANNED_STEPS - store.progress(info.id).steps_done
    assert (est.steps, est.frames) == (left, 2 * left)
    assert est.frame_bytes_source == "measured" and est.bytes == 2 * left * 4096


def test_abort_stops_motion_and_is_final(setup):
    store, rig, info = setup
    r = _runner(store, rig)
    r.bus.subscribe(lambda e: e.kind == EventKind.MOVED and e.step == 2 and r.request_abort())
    assert r.run() == "aborted"
    assert rig.turntable.stops == 1 and rig.polarizer.stops == 1 and rig.positioner.stops == 1
    assert store.session("s").state == "aborted"
    with pytest.raises(RunnerError, match="aborted sessions are final"):
        _runner(store, rig).run()


def test_abort_from_another_thread_during_back_off(setup):
    store, rig, info = setup
    rig.camera.inject("timeout", 1)
    r = Runner(rig, store, "s", retry=RetryPolicy(attempts=3, base_delay_s=30), reserve_bytes=0)
    r.bus.subscribe(lambda e: e.kind == EventKind.RETRY and
                    threading.Timer(0.05, r.request_abort).start())
    assert r.run() == "aborted"  # did not sleep 30 s


def test_low_disk_pauses_cleanly(setup, monkeypatch):
    store, rig, info = setup
    free = {"bytes": 10**12}
    monkeypatch.setattr(store, "free_bytes", lambda: free["bytes"])
    r = Runner(rig, store, "s", retry=FAST_RETRY, reserve_bytes=10**6)
    r.bus.subscribe(lambda e: e.kind == EventKind.FRAME_STORED and e.data["frames_done"] == 6
                    and free.update(bytes=10**6 + 100))
    assert r.run() == "paused"
    kinds = [e["kind"] for e in store.events(info.id)]
    assert "low_disk" in kinds and kinds[-1] == "paused"
    assert store.progress(info.id).steps_done == 3 and store.session("s").state == "paused"
    free["bytes"] = 10**12
    assert r.run() == "done"
    _assert_complete(store, info)


def test_create_session_checks_space_against_estimate(tmp_path, monkeypatch):
    store = Store(tmp_path)
    monkeypatch.setattr(store, "free_bytes", lambda: 50_000)
    with pytest.raises(RunnerError, match="not enough disk space"):
        create_session(store, Plan.from_dict(SMALL_PLAN), make_rig(), reserve_bytes=0)
    assert store.sessions() == []


def test_targets_are_announced_in_order(tmp_path):
    store = Store(tmp_path)
    rig = make_rig()
    plan = Plan.from_dict({**SMALL_PLAN, "calibration": [{"kind": "dark", "frames": 2},
                                                         {"kind": "gray_card", "when": "after"}]})
    create_session(store, plan, rig, name="s", reserve_bytes=0)
    seen = []
    r = Runner(rig, store, "s", reserve_bytes=0, prepare_target=lambda t, step: seen.append(t))
    assert r.run() == "done"
    assert seen == ["dark", "object", "gray_card"]


def test_faulty_subscriber_does_not_stop_the_capture(setup):
    store, rig, info = setup
    r = _runner(store, rig)
    r.bus.subscribe(lambda e: 1 / 0)
    assert r.run() == "done"


def test_unexpected_error_leaves_session_paused(setup, monkeypatch):
    store, rig, info = setup
    monkeypatch.setattr(rig.camera, "capture", lambda: (_ for _ in ()).throw(RuntimeError("bug")))
    with pytest.raises(RuntimeError, match="bug"):
        _runner(store, rig).run()
    assert store.session("s").state == "paused"
    assert [e["kind"] for e in store.events(info.id)][-2:] == ["fault", "paused"]


def test_check_plan_unchanged_lists_differences(setup):
    store, rig, info = setup
    check_plan_unchanged(info, Plan.from_dict(SMALL_PLAN))  # the same plan: no complaint
    changed = Plan.from_dict({**SMALL_PLAN, "polarizer": {"angles_deg": [0, 45]}})
    with pytest.raises(RunnerError, match=r"polarizer.angles_deg: \[0.0, 90.0\] -> \[0.0, 45.0\]"):
        check_plan_unchanged(info, changed)


def test_operator_override_keeps_plan_hash(tmp_path):
    store = Store(tmp_path)
    plan = Plan.from_dict(SMALL_PLAN)
    info = create_session(store, plan, make_rig(), name="s", operator="bo", reserve_bytes=0)
    assert info.operator == "bo" and info.plan_hash == plan.hash


def test_unknown_frame_size_is_measured_from_the_first_frame(tmp_path, monkeypatch):
    # the camera's describe() gives no image size, so 25 MB is assumed; the frames are 30 MB:
    # after the first one the runner re-estimates and pauses cleanly (step 0 done) instead of
    # running the disk full two steps later
    store = Store(tmp_path, durable=False)
    rig = make_rig(frame_bytes=30_000_000)
    monkeypatch.setattr(rig.camera, "describe", lambda: {"driver": "fake"})
    plan = Plan.from_dict({"turntable": {"angles_deg": [0, 10, 20]}, "exposure": {"stops": [0]}})
    info = create_session(store, plan, rig, name="s", reserve_bytes=0)
    free = 80_000_000  # fits 3 assumed frames (75 MB), not 3 real ones (90 MB)
    monkeypatch.setattr(store, "free_bytes", lambda: free - store.progress(info.id).bytes_stored)
    events = []
    r = Runner(rig, store, "s", reserve_bytes=0)
    r.bus.subscribe(events.append)
    assert r.run() == "paused"
    [note] = [e for e in events if e.kind == EventKind.NOTE and "frame size" in e.message]
    assert note.data["frame_bytes"] == 30_000_000 and note.data["assumed_frame_bytes"] == 25_000_000
    assert note.data["bytes_left"] == 2 * 30_000_000
    [low] = [e for e in events if e.kind == EventKind.LOW_DISK]
    assert "re-estimated from the first frame" in low.message
    assert store.progress(info.id).steps_done == 1
    # on resume the stored frames give the size: no second measurement
    free = 10**12
    events.clear()
    assert r.run() == "done"
    assert not [e for e in events if e.kind == EventKind.NOTE and "frame size" in e.message]
    store.close()
