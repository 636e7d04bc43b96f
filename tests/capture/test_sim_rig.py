"""The runner on the simulated lab (real drivers over the real wire protocols, fast mode), with
the simulators' fault injection; and a reader process polling the store while the runner writes."""
from __future__ import annotations

import contextlib
import json
import subprocess
import sys
import textwrap
import threading

import pytest

from capture.events import EventKind
from capture.plan import Plan
from capture.rigs import open_rig
from capture.runner import RetryPolicy, Runner, create_session
from capture.store import Store
from capture_fakes import tolerant_sim_config
from sims.ptp_sim import placeholder_frame

PLAN = {"name": "sim", "turntable": {"angles_deg": [0, 60]},
        "light": {"azimuth_deg": [0, 90], "elevation_deg": [30]},
        "polarizer": {"angles_deg": [0, 90]}, "exposure": {"base_s": 0.01, "stops": [-1, 1]}}
STEPS, FRAMES = 8, 16
RETRY = RetryPolicy(attempts=4, base_delay_s=0.01)


@contextlib.contextmanager
def _open_lab(tmp_path, turntable_timeout_s: float = 5.0):
    """The simulated lab over its real transports, with a session ``s`` planned in a store.

    Reply timeouts are generous (:func:`tolerant_sim_config`): a spurious timeout would be
    retried and break the tests' exact fault expectations. The placeholder DNG stands in for
    the rendered scene: these tests are about the runner."""
    cfg = tolerant_sim_config(turntable_timeout_s)
    with open_rig(cfg, fast=True, home=True, frame_source=placeholder_frame) as opened:
        with Store(tmp_path / "store") as store:
            create_session(store, Plan.from_dict(PLAN), opened.rig, name="s", reserve_bytes=0)
            yield opened, store


@pytest.fixture
def lab(tmp_path):
    with _open_lab(tmp_path) as opened_and_store:
        yield opened_and_store


@pytest.fixture
def lab_quick_turntable_timeout(tmp_path):
    # the injected lost reply costs one reply timeout: keep the turntable's at its default
    with _open_lab(tmp_path, turntable_timeout_s=0.5) as opened_and_store:
        yield opened_and_store


def _complete(store: Store) -> None:
    info = store.session("s")
    assert info.state == "done"
    keys = sorted((f.step, f.bracket_index, f.repeat) for f in store.frames(info.id))
    assert keys == [(s, b, 0) for s in range(STEPS) for b in range(2)]
    assert store.verify("s").ok


def test_session_on_simulated_lab_records_readbacks(lab):
    opened, store = lab
    assert Runner(opened.rig, store, "s", reserve_bytes=0).run() == "done"
    _complete(store)
    info = store.session("s")
    steps = {s.index: s.step for s in store.steps(info.id)}
    for f in store.frames(info.id):
        st = steps[f.step]
        # read-backs from the drivers agree with the plan within the devices' resolution
        assert f.positions["turntable_deg"] == pytest.approx(st.turntable_deg, abs=0.01)
        assert f.positions["polarizer_deg"] == pytest.approx(st.polarizer_deg, abs=0.01)
        x, y, z = f.positions["light_mm"]
        assert z == pytest.approx(500 * 0.5, abs=0.1)  # elevation 30 deg on the 500 mm arm
        assert f.format == "dng" and store.read_object(f.sha256)[:2] in (b"II", b"MM")
        assert f.exposure_s == pytest.approx(f.exposure_requested_s, rel=0.25)  # camera's steps
    describe = store.rig_snapshots(info.id)[0]["describe"]
    assert describe["turntable"]["driver"] == "zaber" and describe["camera"]["driver"] == "ptp"


def test_timeout_mid_session_is_retried(lab_quick_turntable_timeout):
    opened, store = lab_quick_turntable_timeout
    events = []
    r = Runner(opened.rig, store, "s", retry=RETRY, reserve_bytes=0)
    r.bus.subscribe(events.append)

    def swallow(e):
        if e.kind == EventKind.FRAME_STORED and e.data["frames_done"] == 5:
            opened.lab.sims["turntable"].inject("no_reply")
    r.bus.subscribe(swallow)
    assert r.run() == "done"
    retries = [e for e in events if e.kind == EventKind.RETRY]
    assert retries and retries[0].device == "turntable"
    assert retries[0].data["error"] == "DeviceTimeout"
    assert not [e for e in events if e.kind == EventKind.FAULT]
    _complete(store)


def test_disconnect_pauses_with_fault_and_resume_after_reconnect_completes(lab):
    opened, store = lab
    positioner = opened.lab.sims["positioner"]
    events = []
    r = Runner(opened.rig, store, "s", retry=RETRY, reserve_bytes=0)
    r.bus.subscribe(events.append)

    def pull_cable(e):
        if e.kind == EventKind.FRAME_STORED and e.data["frames_done"] == 7:
            positioner.disconnect()
    unsubscribe = r.bus.subscribe(pull_cable)
    assert r.run() == "paused"
    unsubscribe()
    info = store.session("s")
    assert info.state == "paused"
    [fault] = store.events(info.id, kinds=["fault"])
    assert fault["device"] == "positioner" and fault["data"]["error"] == "Disconnected"
    assert not [e for e in events if e.kind == EventKind.RETRY]  # a pulled cable is not retried
    done_before = store.progress(info.id).steps_done
    assert 0 < done_before < STEPS
    positioner.reconnect()  # plugged back in: GRBL powers up unhomed and locked
    assert r.run() == "done"  # reconnects the positioner and homes it again
    notes = [e.message for e in events if e.kind == EventKind.NOTE]
    assert any("homing positioner" in n for n in notes)
    _complete(store)


def test_camera_disconnect_then_resume(lab):
    opened, store = lab
    camera = opened.lab.sims["camera"]
    r = Runner(opened.rig, store, "s", retry=RETRY, reserve_bytes=0)
    r.bus.subscribe(lambda e: e.kind == EventKind.FRAME_STORED and e.data["frames_done"] == 3
                    and camera.disconnect())
    assert r.run() == "paused"
    [fault] = store.events(store.session("s").id, kinds=["fault"])
    assert fault["device"] == "camera"
    camera.reconnect()
    r2 = Runner(opened.rig, store, "s", retry=RETRY, reserve_bytes=0)
    assert r2.run() == "done"
    _complete(store)


READER = textwrap.dedent("""
    import json, sys, time
    from capture.store import Store, sha256_file
    root, total = sys.argv[1], int(sys.argv[2])
    polls, last, bad = 0, -1, []
    deadline = time.monotonic() + 60
    with Store(root, create=False) as st:
        sid = st.session("s").id
        print("ready", flush=True)
        while time.monotonic() < deadline:
            with st._read() as db:  # one snapshot: rows and counts agree
                rows = db.execute("SELECT sha256, size FROM frames WHERE session_id = ?", (sid,)).fetchall()
                done = db.execute("SELECT count(*) FROM steps WHERE session_id = ? AND done = 1", (sid,)).fetchone()[0]
            polls += 1
            for sha, size in rows:
                p = st.object_path(sha)
                if not p.is_file() or p.stat().st_size != size:
                    bad.append(sha)
            if len(rows) < last:
                bad.append(f"count went down {last} -> {len(rows)}")
            last = len(rows)
            if done == int(sys.argv[3]):
                break
            time.sleep(0.005)
        final_ok = all(sha256_file(st.object_path(sha)) == sha for sha, _ in rows)
    print(json.dumps({"polls": polls, "last": last, "bad": bad, "final_ok": final_ok}))
""")


def test_reader_process_sees_consistent_data_while_runner_writes(lab, tmp_path):
    opened, store = lab
    reader = subprocess.Popen([sys.executable, "-c", READER, str(store.root), str(FRAMES), str(STEPS)],
                              stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    assert reader.stdout.readline().strip() == "ready"  # polling before the first write
    # a second in-process reader (another thread, its own connection), as the TUI would
    counts, problems = [], []
    stop = threading.Event()

    def poll():
        with Store(store.root, create=False) as mine:
            while not stop.is_set():
                p = mine.progress(store.session("s").id)
                counts.append(p.frames_stored)
                for f in mine.frames(store.session("s").id):
                    if not mine.object_path(f.sha256).is_file():
                        problems.append(f.sha256)
                stop.wait(0.005)
    t = threading.Thread(target=poll)
    t.start()
    try:
        assert Runner(opened.rig, store, "s", reserve_bytes=0).run() == "done"
    finally:
        stop.set()
        t.join()
    out, err = reader.communicate(timeout=90)
    assert reader.returncode == 0, err
    result = json.loads(out.strip().splitlines()[-1])
    assert result["bad"] == [] and result["final_ok"] and result["last"] == FRAMES
    assert result["polls"] > 1
    assert problems == [] and counts == sorted(counts) and len(counts) > 1
    _complete(store)
