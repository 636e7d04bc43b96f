"""The operator console driven with Textual's pilot against the simulated lab.

Ground truth is the simulators and the store: positions are read back from the devices, frames
counted in the session store, motion checked by reading the position twice.
"""
from __future__ import annotations

import asyncio
import time
from pathlib import Path

import pytest
from textual.widgets import DataTable, Input, ProgressBar

from capture.events import EventBus, EventKind
from capture.runner import Runner, create_session
from capture.plan import Plan
from capture.rigs import home_all, open_rig
from capture.store import Store
from capture.tui import GonioApp
from capture.tui.help import HelpScreen
from capture.tui.session import TargetScreen
from capture.tui.imageview import HalfBlockImage, HistogramView
from sims.ptp_sim import placeholder_frame

PLAN = """
name = "{name}"
[turntable]
angles_deg = {angles}
[light]
azimuth_deg = [0]
elevation_deg = [30]
[polarizer]
angles_deg = [0]
[exposure]
base_s = 0.01
stops = {stops}
"""

#: real-time simulation with a turntable slow enough for multi-second moves
#: the camera's stand-in frame (a noisy gradient, ~20 ms) instead of a scene render (~0.4 s):
#: for tests about the session flow rather than the image
QUICK_CAMERA = {"camera": {"frame_source": placeholder_frame}}
#: real-time simulation with a turntable slow enough for multi-second moves
SLOW_TURNTABLE = {"turntable": {"speed_deg_s": 30.0, "accel_deg_s2": 60.0}, **QUICK_CAMERA}


def make_app(*args, **kwargs) -> GonioApp:
    """The console with animations off (the pilot waits for each one to finish). With the stand-in
    camera there is no scene to set up, so nobody is asked to (a frame source of one's own has
    no scene changer: the console would wait for the operator at every target)."""
    if "frame_source" in (kwargs.get("sim_options") or {}).get("camera", {}):
        kwargs.setdefault("prompt_targets", False)
    app = GonioApp(*args, **kwargs)
    app.animation_level = "none"
    return app


def write_plan(tmp_path: Path, name: str = "t", angles=(0, 90), stops=(0,)) -> Path:
    path = tmp_path / f"{name}.toml"
    path.write_text(PLAN.format(name=name, angles=list(angles), stops=list(stops)))
    return path


async def until(pilot, cond, timeout: float = 15.0, what: str = "condition") -> None:
    """Let the app run until ``cond()`` holds (raises after ``timeout`` seconds)."""
    deadline = time.monotonic() + timeout
    while not cond():
        if time.monotonic() > deadline:
            recent = "\n".join(f"  {e.kind} [{e.device}] {e.message}"
                               for e in list(pilot.app.log_pane.entries)[-8:])
            raise AssertionError(f"timed out after {timeout} s waiting for {what}; "
                                 f"last log lines:\n{recent}")
        await pilot.pause(0.02)


async def settled(sim, timeout: float = 3.0) -> float:
    """The simulated turntable's angle once it has stopped (unchanged over 0.2 s), degrees."""
    deadline = time.monotonic() + timeout
    angle = sim.angle_deg
    while True:
        await asyncio.sleep(0.2)
        now = sim.angle_deg
        if now == pytest.approx(angle, abs=1e-6):
            return now
        if time.monotonic() > deadline:
            raise AssertionError(f"the turntable is still moving after {timeout} s")
        angle = now


def cell(app: GonioApp, row: str, column: str) -> str:
    return str(app.query_one("#device-table", DataTable).get_cell(row, column))


async def connected(pilot, app: GonioApp) -> None:
    await until(pilot, lambda: app.rig is not None and cell(app, "camera", "link") == "connected",
                what="the rig to connect")


async def select_row(pilot, app: GonioApp, key: str) -> None:
    table = app.query_one("#device-table", DataTable)
    table.focus()
    table.move_cursor(row=table.get_row_index(key))
    await pilot.pause()


async def home_everything(pilot, app: GonioApp) -> None:
    await pilot.press("1", "H")
    await until(pilot, lambda: cell(app, "turntable", "homed") == "yes"
                and cell(app, "positioner.az", "homed") == "yes", what="homing")


async def start_session(pilot, app: GonioApp, plan: Path) -> None:
    await pilot.press("2")
    app.query_one("#plan-path", Input).value = str(plan)
    await pilot.press("o")
    await until(pilot, lambda: app.plan is not None, what="the plan to load")
    await pilot.press("n")
    await until(pilot, lambda: app.runner is not None, what="the session to start")


def store_state(store_dir: Path, name: str) -> tuple[str, int, int]:
    """(state, steps done, frames stored) of a session, read from the store."""
    with Store(store_dir) as store:
        info = store.session(name)
        p = store.progress(info.id)
        return info.state, p.steps_done, len(store.frames(info.id))


@pytest.mark.asyncio
async def test_connect_jog_and_home_an_axis(tmp_path):
    app = make_app("sim", tmp_path / "store", fast=True)
    async with app.run_test(size=(80, 24)) as pilot:
        await connected(pilot, app)
        for key in ("turntable", "positioner.az", "polarizer", "camera"):
            assert cell(app, key, "link") == "connected"
        assert "Zaber" in cell(app, "turntable", "model")
        assert cell(app, "turntable", "homed") == "NO"
        await select_row(pilot, app, "turntable")
        # an unhomed Zaber rejects moves: the fault is shown, not raised
        await pilot.press("plus")
        await until(pilot, lambda: "reference" in cell(app, "turntable", "fault"),
                    what="the NotHomed fault")
        await pilot.press("h")
        await until(pilot, lambda: cell(app, "turntable", "homed") == "yes", what="homing")
        assert cell(app, "turntable", "fault") == ""  # a successful home clears it
        await pilot.press("right_square_bracket", "right_square_bracket")  # 1 -> 5 -> 10 deg
        assert app.devices_pane.jog_step == 10.0
        await pilot.press("plus", "plus", "minus")
        await until(pilot, lambda: cell(app, "turntable", "position") == "10.000 deg",
                    what="the jogs to finish")
        assert app.rig.turntable.position == pytest.approx(10.0, abs=1e-3)
        assert app.lab.sims["turntable"].angle_deg == pytest.approx(10.0, abs=1e-3)
        # go to, typed into the input
        await pilot.press("g")
        for ch in "123.5":
            await pilot.press(ch)
        await pilot.press("enter")
        await until(pilot, lambda: cell(app, "turntable", "position") == "123.500 deg",
                    what="go to 123.5")
        assert app.lab.sims["turntable"].angle_deg == pytest.approx(123.5, abs=1e-3)
        # the positioner: home all, then jog the light's elevation
        await home_everything(pilot, app)
        await select_row(pilot, app, "positioner.el")
        el0 = app.devices_pane.states["positioner.el"].value
        await pilot.press("plus")
        await until(pilot, lambda: app.devices_pane.states["positioner.el"].value
                    == pytest.approx(el0 + 10.0, abs=0.05), what="the elevation jog")


@pytest.mark.asyncio
async def test_test_shot_updates_preview_and_histogram_warns(tmp_path):
    app = make_app("sim", tmp_path / "store", fast=True)
    async with app.run_test(size=(100, 30)) as pilot:
        await connected(pilot, app)
        image = app.query_one(HalfBlockImage)
        assert image.preview is None
        await pilot.press("t")
        await until(pilot, lambda: image.preview is not None, what="the preview")
        shot = app.last_frames[0]
        assert shot.exposure_s == pytest.approx(0.01)
        # 1/100 s clips at most the lamp's highlight on the glossy object (seen: 0.04 %)
        assert shot.preview.histogram.clipped_white_pct.max() < 0.2
        await pilot.press("3")
        await until(pilot, lambda: image.rendered, what="the half-block image")
        line = image.render_line(image.size.height // 2)
        assert "▀" in line.text and image.size.width > 0
        # a 100x longer exposure saturates: the histogram says so, per channel
        await pilot.press("1", "e", "1", "enter")
        await until(pilot, lambda: cell(app, "camera", "position").startswith("1 s"),
                    what="the exposure read-back")
        await pilot.press("t")
        await until(pilot, lambda: app.last_frames[0] is not shot, what="the second shot")
        hist = app.last_frames[0].preview.histogram
        assert hist.clipped_white_pct.min() > 1  # the lit object saturates (the background stays dark)
        await until(pilot, lambda: len(app.query(HistogramView)) == 1
                    and "clipped white" in str(app.query_one(HistogramView).render()),
                    what="the clipping warning")
        assert any(e.kind == "camera" and "clipped white" in e.message
                   for e in app.log_pane.entries)


@pytest.mark.asyncio
async def test_session_runs_to_100_percent_with_bracket_preview(tmp_path):
    plan = write_plan(tmp_path, angles=(0, 90, 180), stops=(-1, 0, 1))
    bus = EventBus()
    app = make_app("sim", tmp_path / "store", fast=True, sim_options=QUICK_CAMERA, bus=bus)
    async with app.run_test(size=(80, 24)) as pilot:
        await connected(pilot, app)
        await home_everything(pilot, app)
        # one swallowed request after step 0: a timeout the runner retries and gets past
        bus.subscribe(lambda ev: ev.kind == EventKind.STEP_DONE and ev.step == 0
                      and app.lab.sims["turntable"].inject("no_reply"))
        await start_session(pilot, app, plan)
        pane = app.session_pane
        await until(pilot, lambda: pane.state == "done", timeout=30, what="the session")
        bar = app.query_one("#progress", ProgressBar)
        assert bar.percentage == 1.0
        assert "3/3 steps" in str(app.query_one("#progress-text").render())
        assert pane.frames_stored == 9
        await until(pilot, lambda: len(app.query(HistogramView)) == 3, what="the bracket")
        assert [v.frame.exposure_s for v in app.query(HistogramView)] == \
            pytest.approx([0.005, 0.01, 0.02])
        state, steps_done, frames = store_state(tmp_path / "store", app.runner.name)
        assert (state, steps_done, frames) == ("done", 3, 9)
        kinds = [e.kind for e in app.log_pane.entries]
        assert kinds.count("frame_stored") == 9 and "done" in kinds
        # the fault table says what the runner did about the timeout
        (event, action), = pane.faults
        assert event.kind == EventKind.RETRY and event.device == "turntable"
        assert action.startswith("retried (1,")
        assert pane.alert_text is None


@pytest.mark.asyncio
async def test_pause_resume_and_abort_stops_motion(tmp_path):
    # real motion time: steps 1 and 2 turn the turntable by 170 / 160 deg at 30 deg/s (~6 s)
    plan = write_plan(tmp_path, angles=(0, 170, 10))
    app = make_app("sim", tmp_path / "store", fast=False, sim_options=SLOW_TURNTABLE)
    async with app.run_test(size=(80, 24)) as pilot:
        await connected(pilot, app)
        await home_everything(pilot, app)
        await start_session(pilot, app, plan)
        await pilot.press("p")  # pause after the current step
        pane = app.session_pane
        await until(pilot, lambda: pane.state == "paused" and not app.runner_active,
                    timeout=20, what="the pause")
        name = app.runner.name
        state, done_at_pause, frames = store_state(tmp_path / "store", name)
        assert state == "paused" and done_at_pause in (1, 2) and frames == done_at_pause
        assert "paused" in str(app.query_one("#statusbar").render())
        await pilot.press("p")  # resume
        await until(pilot, lambda: pane.state == "running", what="resumed")
        assert any(e.kind == "resumed" for e in app.log_pane.entries)
        # abort while the turntable is on its way (to 170 deg, or back to 10)
        sim = app.lab.sims["turntable"]
        await until(pilot, lambda: 20 < sim.angle_deg < 150, timeout=20, what="a move under way")
        await pilot.press("a")  # once: only a warning, the move goes on
        assert pane.state == "running"
        await pilot.press("a")
        await until(pilot, lambda: pane.state == "aborted", timeout=10, what="the abort")
        a1 = await settled(sim)
        assert 11 < a1 < 169, "the move was not cut short"
        assert store_state(tmp_path / "store", name) == ("aborted", done_at_pause, done_at_pause)


@pytest.mark.asyncio
async def test_device_fault_shows_alert_and_pauses_then_resumes(tmp_path):
    plan = write_plan(tmp_path, angles=(0, 90, 180, 270))
    bus = EventBus()  # the runner's own bus, so the fault lands at a known point
    app = make_app("sim", tmp_path / "store", fast=True, bus=bus, sim_options=QUICK_CAMERA)
    async with app.run_test(size=(80, 24)) as pilot:
        await connected(pilot, app)
        await home_everything(pilot, app)
        # when step 1 is done, pull the turntable's cable: its next request fails
        bus.subscribe(lambda ev: ev.kind == EventKind.STEP_DONE and ev.step == 1
                      and app.lab.sims["turntable"].inject("disconnect"))
        await start_session(pilot, app, plan)
        pane = app.session_pane
        await until(pilot, lambda: pane.state == "paused" and not app.runner_active,
                    what="the fault pause")
        assert pane.alert_text is not None and "turntable" in pane.alert_text
        assert any(n.severity == "error" and "turntable" in n.message
                   for n in app._notifications)
        assert "turntable" in [event.device for event, _ in pane.faults]
        assert any(e.kind == "fault" and e.level >= 40 and e.device == "turntable"
                   for e in app.log_pane.entries)
        await until(pilot, lambda: cell(app, "turntable", "link") == "lost",
                    what="the device table to show the lost link")
        assert store_state(tmp_path / "store", app.runner.name)[:2] == ("paused", 2)
        # the operator plugs the cable back in; the stage powered up without a reference, so:
        # reconnect (c) and home (h) it on the Devices tab, then resume (p) the session
        app.lab.sims["turntable"].reconnect()
        await select_row(pilot, app, "turntable")
        await pilot.press("c")
        await until(pilot, lambda: cell(app, "turntable", "link") == "connected",
                    what="the reconnect")
        await pilot.press("h")
        await until(pilot, lambda: cell(app, "turntable", "homed") == "yes", what="homing")
        await pilot.press("2", "p")
        await until(pilot, lambda: pane.state == "done", timeout=30, what="the resumed session")
        assert pane.alert_text is None
        assert store_state(tmp_path / "store", app.runner.name) == ("done", 4, 4)


@pytest.mark.asyncio
async def test_scene_change_prompt_holds_the_runner_until_the_operator_answers(tmp_path):
    plan = write_plan(tmp_path, angles=(0, 90))
    app = make_app("sim", tmp_path / "store", fast=True, sim_options=QUICK_CAMERA,
                   prompt_targets=True)  # as on a real rig
    async with app.run_test(size=(80, 24)) as pilot:
        await connected(pilot, app)
        await home_everything(pilot, app)
        await start_session(pilot, app, plan)
        await until(pilot, lambda: isinstance(app.screen, TargetScreen), what="the prompt")
        assert app.screen.target == "object"
        await pilot.pause(0.3)
        name = app.runner.name
        assert store_state(tmp_path / "store", name)[2] == 0  # nothing captured while asking
        await pilot.press("escape")  # not ready: the session pauses before anything moves
        await until(pilot, lambda: app.session_pane.state == "paused" and not app.runner_active,
                    what="the pause")
        assert store_state(tmp_path / "store", name) == ("paused", 0, 0)
        await pilot.press("2", "p")  # resume: asked again, ready this time
        await until(pilot, lambda: isinstance(app.screen, TargetScreen), what="the prompt again")
        await pilot.press("enter")
        await until(pilot, lambda: app.session_pane.state == "done", what="the session")
        assert store_state(tmp_path / "store", name) == ("done", 2, 2)


@pytest.mark.asyncio
async def test_resume_an_interrupted_session_is_one_key(tmp_path):
    store_dir = tmp_path / "store"
    plan = Plan.from_toml(write_plan(tmp_path, angles=(0, 60, 120, 180)))
    # a first process captured one step, then died (the store still says "running")
    with open_rig("sim", fast=True, options=QUICK_CAMERA) as opened, Store(store_dir) as store:
        home_all(opened.rig)
        info = create_session(store, plan, opened.rig, name="crashed")
        runner = Runner(opened.rig, store, info)
        runner.bus.subscribe(lambda ev: ev.kind == EventKind.STEP_DONE and runner.request_pause())
        assert runner.run() == "paused"
        store.set_state(info.id, "running")
    assert store_state(store_dir, "crashed") == ("running", 1, 1)

    app = make_app("sim", store_dir, fast=True, sim_options=QUICK_CAMERA)
    async with app.run_test(size=(80, 24)) as pilot:
        await connected(pilot, app)
        await home_everything(pilot, app)
        await pilot.press("2")
        sessions = app.query_one("#sessions", DataTable)
        await until(pilot, lambda: sessions.row_count == 1, what="the session list")
        assert str(sessions.get_cell("crashed", "state")) == "interrupted"  # no writer left
        await pilot.press("r")
        await until(pilot, lambda: app.session_pane.state == "done", timeout=30,
                    what="the resumed session")
        assert any(e.kind == "resumed" for e in app.log_pane.entries)
        assert not any(e.kind == "session_started" for e in app.log_pane.entries)
        await until(pilot, lambda: str(sessions.get_cell("crashed", "state")) == "done",
                    what="the list to refresh")
    assert store_state(store_dir, "crashed") == ("done", 4, 4)


@pytest.mark.asyncio
async def test_keys_answer_within_100_ms_during_a_long_move_and_estop_stops_it(tmp_path):
    # 10 deg/s: the pilot waits for the process to go idle after each key, which it never
    # does while the in-process simulators run a move, so every press returns after ~2 s
    very_slow = {**SLOW_TURNTABLE, "turntable": {"speed_deg_s": 10.0, "accel_deg_s2": 20.0}}
    app = make_app("sim", tmp_path / "store", fast=False, sim_options=very_slow)
    async with app.run_test(size=(80, 24)) as pilot:
        await connected(pilot, app)
        await home_everything(pilot, app)
        await select_row(pilot, app, "turntable")
        await pilot.press("g", "1", "7", "0", "enter")  # 170 deg at 10 deg/s: ~17 s
        sim = app.lab.sims["turntable"]
        await until(pilot, lambda: 1 < sim.angle_deg < 60, what="the move to start")

        pane, tabs = app.devices_pane, app.query_one("#tabs")
        stamps: list[float] = []
        # the handler's effect is a reactive change; its watcher stamps the time it happens
        app.watch(pane, "step_index", lambda _: stamps.append(time.perf_counter()), init=False)
        app.watch(tabs, "active", lambda _: stamps.append(time.perf_counter()), init=False)
        delays = []
        for key in ("right_square_bracket", "left_square_bracket", "2", "1"):
            stamps.clear()
            t0 = time.perf_counter()
            await pilot.press(key)
            assert stamps, f"key {key!r} had no effect"
            delays.append(stamps[0] - t0)
        assert pane.step_index == 1 and tabs.active == "devices"
        assert sim.angle_deg < 150, "the move ended before the keys were measured"
        assert max(delays) < 0.1, f"key handling took {max(delays) * 1000:.0f} ms"
        # emergency stop: the stage decelerates and stays short of 170 deg
        await pilot.press("ctrl+e")
        a1 = await settled(sim)
        assert a1 < 169, "the move was not cut short"
        assert any(e.kind == "estop" for e in app.log_pane.entries)


@pytest.mark.asyncio
async def test_log_filters_and_help_screen(tmp_path):
    app = make_app("sim", tmp_path / "store", fast=True)
    async with app.run_test(size=(80, 24)) as pilot:
        await connected(pilot, app)
        await select_row(pilot, app, "turntable")
        await pilot.press("plus")  # unhomed: an ERROR line of kind "device"
        await until(pilot, lambda: any(e.level >= 40 for e in app.log_pane.entries),
                    what="the error line")
        await pilot.press("4")
        log = app.log_pane
        everything = len(log.visible)
        log.query_one("#log-level").value = 40  # errors only
        await pilot.pause()
        assert 0 < len(log.visible) < everything
        assert all(e.level >= 40 for e in log.visible)
        assert len(log.query_one("#log-view").lines) >= len(log.visible)
        log.query_one("#log-level").value = 10
        log.query_one("#log-kind").value = "console"
        await pilot.pause()
        assert log.visible and all(e.kind == "console" for e in log.visible)
        await pilot.press("f1")
        assert isinstance(app.screen, HelpScreen)
        await pilot.press("q")
        assert not isinstance(app.screen, HelpScreen)


@pytest.mark.asyncio
async def test_layout_fits_80x24_and_scales(tmp_path):
    app = make_app("sim", tmp_path / "store", fast=True)
    async with app.run_test(size=(80, 24)) as pilot:
        await connected(pilot, app)
        table = app.query_one("#device-table", DataTable)
        assert table.region.height >= 6 and table.region.bottom <= 24  # all five rows visible
        await pilot.press("2")
        assert app.query_one("#steps").region.height >= 3
        await pilot.resize_terminal(160, 48)
        await pilot.pause()
        assert app.query_one("#steps").region.height >= 20
