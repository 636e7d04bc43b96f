"""The gonio operator console: a Textual app over the same rig, store and runner as the CLI.

Threads: the UI thread only draws. Every device request, plan load, store query and the capture
runner itself run in Textual thread workers; they report back with messages (``post_message``
is thread-safe). The runner's events arrive through its event bus and are forwarded as
:class:`RunnerEvent` messages.
"""
from __future__ import annotations

import contextlib
import functools
import inspect
import logging
import threading
import time
from pathlib import Path
from typing import Any

from rich.text import Text
from textual import work
from textual.app import App, ComposeResult
from textual.binding import Binding
from textual.message import Message
from textual.widgets import DataTable, Footer, Header, Static, TabbedContent, TabPane

from rig.device import Axis, Frame, LightPositioner, LightTarget
from rig.errors import Disconnected, RigError
from rig.rig import Rig

from ..events import Event, EventKind
from ..plan import Step, step_prompt
from ..preview import PreviewError, make_preview
from ..runner import RunnerError
from ..store import StoredStep, StoreError
from . import backend
from .devices import ROWS, DeviceRequest, DevicesPane, DeviceState, light_direction, snapshot
from .help import HelpScreen
from .imageview import PreviewFrame, PreviewPane
from .logpane import LogEntry, LogPane
from .session import SessionPane, SessionRequest, TargetScreen


#: longest a console-initiated move or homing run may take before it is reported, seconds
MOVE_TIMEOUT_S = 300.0


def _while_attached(handler):
    """Drop worker messages that arrive after the app has begun tearing its widgets down."""
    @functools.wraps(handler)
    async def wrapper(self, message):
        if self.devices_pane.is_attached:
            result = handler(self, message)
            if inspect.isawaitable(result):
                await result
    return wrapper


# -- messages from workers --------------------------------------------------------------------
class RigReady(Message):
    def __init__(self, rig: Rig, info: dict[str, dict[str, Any]]) -> None:
        super().__init__()
        self.rig, self.info = rig, info


class RigFailed(Message):
    def __init__(self, error: BaseException) -> None:
        super().__init__()
        self.error = error


class DeviceStates(Message):
    """Fresh rows for the device table; ``errors`` maps a role to the error its poll raised."""

    def __init__(self, states: list[DeviceState], errors: dict[str, RigError]) -> None:
        super().__init__()
        self.states, self.errors = states, errors


class ActionResult(Message):
    """A device request finished: ``error`` is None on success."""

    def __init__(self, op: str, key: str, text: str, error: BaseException | None = None) -> None:
        super().__init__()
        self.op, self.key, self.text, self.error = op, key, text, error


class FramesReady(Message):
    """Decoded frames for the preview (a test shot, or the frames of a session step so far);
    ``test_shot`` frames also get their clipping warnings logged."""

    def __init__(self, frames: list[PreviewFrame], *, test_shot: bool = False) -> None:
        super().__init__()
        self.frames, self.test_shot = frames, test_shot


class RunnerEvent(Message):
    """One event of the capture runner, forwarded from its thread."""

    def __init__(self, event: Event) -> None:
        super().__init__()
        self.event = event


class SessionLoaded(Message):
    """A plan or a session was read: its steps (None: unchanged) and a summary line, and the
    sessions of the store."""

    def __init__(self, steps: list[StoredStep] | None, summary: str,
                 sessions: list[tuple[str, str, str]]) -> None:
        super().__init__()
        self.steps, self.summary, self.sessions = steps, summary, sessions


class SessionOpened(Message):
    """A runner was made for a new or resumed session."""

    def __init__(self, runner: Any) -> None:
        super().__init__()
        self.runner = runner


class SessionEnded(Message):
    """``Runner.run()`` returned ``state`` (done, paused, aborted), or raised ``error``."""

    def __init__(self, state: str, error: BaseException | None = None) -> None:
        super().__init__()
        self.state, self.error = state, error


class ProcessProgress(Message):
    """``gonio process`` of ``session`` reached ``stage`` (``done`` of ``total``)."""

    def __init__(self, session: str, stage: str, done: int, total: int) -> None:
        super().__init__()
        self.session, self.stage, self.done, self.total = session, stage, done, total


class ProcessEnded(Message):
    """Processing ``session`` finished with ``report`` (a ``ProcessReport``) or ``error``."""

    def __init__(self, session: str, report: Any = None, error: BaseException | None = None) -> None:
        super().__init__()
        self.session, self.report, self.error = session, report, error


class TargetCancelled(RunnerError):
    """The operator cancelled a scene-change prompt; the runner pauses the session."""


class GonioApp(App[None]):
    """The operator console.

    Parameters
    ----------
    rig : str
        ``"sim"`` for the simulated lab, or a rig TOML file.
    store : str or Path
        Session store directory (created if missing).
    fast : bool
        Simulated lab only: moves complete at once (tests, demos).
    poll_s : float
        Device table refresh period while no session runs, seconds.
    plan : str or Path, optional
        A plan file to open at start.
    sim_options : dict, optional
        Simulated devices only: settings per role, e.g. ``{"turntable": {"speed_deg_s": 30}}``.
    prompt_targets : bool, optional
        Ask the operator to set up each scene target (lens cap, checkerboard ...) before the
        steps that need it. Default: on a real rig; the simulated lab swaps its scene itself.
    **runner_options
        Passed to :class:`capture.runner.Runner` (``retry=``, ``move_timeout_s=`` ...).
    """

    CSS_PATH = "app.tcss"
    TITLE = "gonio"
    SUB_TITLE = "operator console"
    BINDINGS = [
        Binding("ctrl+e,f12", "emergency_stop", "E-STOP", priority=True),
        Binding("1", "show_tab('devices')", "Devices"),
        Binding("2", "show_tab('session')", "Session"),
        Binding("3", "show_tab('preview')", "Preview"),
        Binding("4", "show_tab('log')", "Log"),
        Binding("f1,question_mark", "help", "Help"),
        Binding("ctrl+q", "quit", "Quit", priority=True),
    ]

    def __init__(self, rig: str = "sim", store: str | Path = "gonio-store", *, fast: bool = False,
                 poll_s: float = 0.25, plan: str | Path | None = None,
                 sim_options: dict[str, dict[str, Any]] | None = None,
                 prompt_targets: bool | None = None, process_options: dict[str, Any] | None = None,
                 **runner_options: Any) -> None:
        super().__init__()
        #: what ``process`` takes besides the session: ``mesh`` (trimesh; not for sessions of
        #: the built-in simulated lab), ``methods`` ...
        self.process_options = dict(process_options or {})
        self.processing: str | None = None   # the session being processed
        self.rig_spec = rig
        self.store_dir = Path(store)
        self.fast = fast
        self.poll_s = poll_s
        self.sim_options = sim_options
        self.prompt_targets = prompt_targets
        self._target_reply = threading.Event()  # set when the operator answers a scene prompt
        self._target_ready = False
        self.rig: Rig | None = None
        self.opened: Any = None         # capture.rigs.OpenedRig: the rig and its SimLab, if any
        self.store: Any = None
        self.runner: Any = None
        self.plan: Any = None
        self.plan_path: str | None = None if plan is None else str(plan)
        self.runner_active = False      # a worker is inside Runner.run()
        self._runner_idle = threading.Event()
        self._runner_idle.set()
        self.runner_options = dict(runner_options)
        self.info: dict[str, dict[str, Any]] = {}
        self.last_frames: list[PreviewFrame] = []
        self._preview_cache: dict[str, Any] = {}
        self._cache_lock = threading.Lock()
        self._polling = threading.Lock()
        self._device_locks: dict[str, threading.Lock] = {}

    # -- layout -------------------------------------------------------------------------------
    def compose(self) -> ComposeResult:
        yield Header()
        # kept as attributes: handlers reach them even while the help screen is on top
        self.devices_pane = DevicesPane(id="devices-pane")
        self.session_pane = SessionPane(id="session-pane")
        self.preview_pane = PreviewPane(id="preview-pane")
        self.log_pane = LogPane(id="log-pane")
        with TabbedContent(initial="devices", id="tabs"):
            with TabPane("1 Devices", id="devices"):
                yield self.devices_pane
            with TabPane("2 Session", id="session"):
                yield self.session_pane
            with TabPane("3 Preview", id="preview"):
                yield self.preview_pane
            with TabPane("4 Log", id="log"):
                yield self.log_pane
        self.statusbar = Static(id="statusbar")
        yield self.statusbar
        yield Footer()

    @property
    def lab(self) -> Any:
        """The SimLab behind ``--rig sim`` (None for real hardware or before connecting)."""
        return None if self.opened is None else self.opened.lab

    def on_mount(self) -> None:
        self.query_one("#device-table", DataTable).focus()
        self.watch(self.session_pane, "state", self._update_status)
        self.log_line(logging.INFO, "console", f"opening rig {self.rig_spec!r}, store {self.store_dir}")
        self.open_rig()
        self.open_store(self.plan_path)
        self.set_interval(self.poll_s, self.poll_devices)

    def _update_status(self, *_: Any) -> None:
        """The always-visible line: the E-STOP key, the rig, the session."""
        rig = (f"{len(self.rig.devices)} devices" if self.rig is not None else "not connected")
        pane = self.session_pane
        session = pane.state if pane.session_name is None else f"{pane.session_name} {pane.state}"
        text = Text.assemble(("ctrl+e E-STOP", "bold white on red"),
                             f"  rig {self.rig_spec}: {rig}  │  session: ", (session, "bold"),
                             no_wrap=True, overflow="ellipsis")
        self.statusbar.update(text)

    def log_line(self, level: int, kind: str, message: str, device: str | None = None) -> None:
        self.log_pane.add(LogEntry(level, kind, message, device))

    # -- global actions -----------------------------------------------------------------------
    def action_show_tab(self, tab: str) -> None:
        if isinstance(self.screen, HelpScreen):
            self.pop_screen()
        self.query_one(TabbedContent).active = tab
        focus = {"devices": "#device-table", "session": "#steps", "preview": "#histograms",
                 "log": "#log-view"}[tab]
        self.query_one(focus).focus()

    def action_help(self) -> None:
        if not isinstance(self.screen, HelpScreen):
            self.push_screen(HelpScreen())

    def action_emergency_stop(self) -> None:
        """Stop every axis at once; a running session is paused first so it moves no further."""
        if self.runner_active:
            self.runner.request_pause(now=True)  # stops the rig too, and moves no further
        self.log_line(logging.ERROR, "estop", "EMERGENCY STOP: stopping every axis")
        self.notify("EMERGENCY STOP: all axes stopping", severity="error", timeout=5, markup=False)
        self._estop()

    @work(thread=True, group="estop")
    def _estop(self) -> None:
        if self.rig is None:
            return
        try:
            self.rig.stop_all()
            self.post_message(ActionResult("estop", "", "all axes stopped"))
        except RigError as exc:
            self.post_message(ActionResult("estop", "", "stop failed", exc))

    async def action_quit(self) -> None:
        if self.runner_active:  # leave the session paused (resumable), not half-running
            self.runner.request_pause(now=True)
        self.exit()

    def on_unmount(self) -> None:
        if self.runner_active:
            self.runner.request_pause(now=True)
            self._target_ready = False  # a pending scene prompt counts as cancelled
            self._target_reply.set()
        # let the runner record its pause before the devices go away under it
        self._runner_idle.wait(timeout=10)
        self.workers.cancel_all()
        if self.opened is not None:
            self.opened.close()

    # -- rig ----------------------------------------------------------------------------------
    @work(thread=True, exclusive=True, group="connect")
    def open_rig(self) -> None:
        for attempt in range(1, 4):
            try:
                opened = backend.open_rig(self.rig_spec, fast=self.fast,
                                          sim_options=self.sim_options)
                info = {role: dev.describe() for role, dev in opened.rig.devices.items()}
                break
            except RigError as exc:
                if not exc.retryable or attempt == 3:
                    self.post_message(RigFailed(exc))
                    return
                time.sleep(0.5 * attempt)  # a slow answer at power-up: try again
            except (OSError, ValueError) as exc:
                self.post_message(RigFailed(exc))
                return
        self.opened = opened
        self.post_message(RigReady(opened.rig, info))

    @_while_attached
    def on_rig_ready(self, message: RigReady) -> None:
        self.rig, self.info = message.rig, message.info
        for key, (role, _) in ROWS.items():
            if role not in self.info:
                self.devices_pane.set_absent(key)
        names = ", ".join(f"{r} ({d.get('model', d.get('driver'))})" for r, d in self.info.items())
        self.log_line(logging.INFO, "console", f"rig connected: {names}")
        self._update_status()
        self.notify("rig connected", markup=False)
        self.poll_devices()

    @_while_attached
    def on_rig_failed(self, message: RigFailed) -> None:
        self.log_line(logging.ERROR, "console", f"cannot open the rig: {message.error}")
        self.notify(f"cannot open the rig: {message.error}", severity="error", timeout=10, markup=False)
        self._update_status()

    def poll_devices(self) -> None:
        """Refresh the device table (skipped while a session runs: its events carry positions,
        and the runner must be the only one talking to the devices)."""
        if self.rig is None or self.runner_active or self._polling.locked():
            return
        self._poll()

    @work(thread=True, group="poll")
    def _poll(self) -> None:
        if not self._polling.acquire(blocking=False):
            return
        try:
            states, errors = [], {}
            for role, device in self.rig.devices.items():
                try:
                    states += snapshot(role, device, self.info.get(role, {}))
                except RigError as exc:
                    errors[role] = exc
                except Exception as exc:  # noqa: BLE001 - a driver bug must not end the console
                    errors[role] = RigError(f"{type(exc).__name__}: {exc}", device=role)
            self.post_message(DeviceStates(states, errors))
        finally:
            self._polling.release()

    @_while_attached
    def on_device_states(self, message: DeviceStates) -> None:
        pane = self.devices_pane
        for state in message.states:
            pane.set_state(state)
        for role, exc in message.errors.items():
            if pane.faults.get(role) != exc.message:
                self.log_line(logging.ERROR, "device", str(exc), device=role)
            pane.set_fault(role, exc.message)
            if isinstance(exc, Disconnected):
                pane.set_disconnected(role)

    # -- device requests ----------------------------------------------------------------------
    def on_device_request(self, request: DeviceRequest) -> None:
        op = request.op
        if op == "connect" and self.rig is None:
            self.open_rig()
            return
        if self.rig is None:
            self.notify("the rig is not connected yet", severity="warning", markup=False)
            return
        if self.runner_active and op != "stop":
            self.notify("a session is running: pause (p) or abort (a) it first", severity="warning", markup=False)
            return
        role = ROWS[request.key][0] if request.key else ""
        if role and getattr(self.rig, role) is None:
            self.notify(f"no {role} in this rig", severity="warning", markup=False)
            return
        what = op if request.value is None else f"{op} {request.value:g}"
        self.log_line(logging.INFO, "camera" if role == "camera" else "device", what,
                      device=role or None)
        if op in ("jog", "goto", "home"):
            self.devices_pane.set_busy(request.key, True)
        self._device_action(op, request.key, request.value)

    @work(thread=True)
    def _device_action(self, op: str, key: str, value: float | None) -> None:
        role = ROWS[key][0] if key else ""
        # requests to one device run in order (three jog presses add up); stop never waits
        lock = (contextlib.nullcontext() if op == "stop" or not role
                else self._device_locks.setdefault(role, threading.Lock()))
        try:
            with lock:
                text = self._do(op, key, value)
        except Exception as exc:  # noqa: BLE001 - one failed request must not take the console down
            self.post_message(ActionResult(op, key, "", exc))
            return
        self.post_message(ActionResult(op, key, text))

    def _do(self, op: str, key: str, value: float | None) -> str:
        """One device request, blocking (worker thread). Returns a line for the log."""
        if op == "home_all":
            return backend.home_every_axis(self.rig)
        role, sub = ROWS[key]
        device = getattr(self.rig, role)
        if op == "connect":  # after a cable was pulled and plugged back
            device.close()
            device.connect()
            self.info[role] = device.describe()
            return "reconnected"
        if op == "stop":
            device.stop()
            return "stopped"
        if op == "home":
            device.home().wait(MOVE_TIMEOUT_S)
            return "homed"
        if op in ("exposure", "iso"):
            took = device.set_exposure(value) if op == "exposure" else device.set_iso(value)
            return f"{op} set to {took:g}" + (" s" if op == "exposure" else "")
        if op == "test_shot":
            frame = device.capture()
            self.post_message(FramesReady([self._decode(frame, "test shot")], test_shot=True))
            return f"test shot {frame.filename}: {len(frame.data) / 1e6:.1f} MB"
        if isinstance(device, LightPositioner):
            az, el, _ = light_direction(device.light_position_mm)
            if op == "jog":
                az, el = (az + value, el) if sub == "az" else (az, el + value)
            else:
                az, el = (value, el) if sub == "az" else (az, value)
            device.move_to(LightTarget(azimuth_deg=az, elevation_deg=el)).wait(MOVE_TIMEOUT_S)
            az, el, _ = light_direction(device.light_position_mm)
            return f"light at az {az:.2f}° el {el:.2f}°"
        assert isinstance(device, Axis)
        status = device.move_by(value) if op == "jog" else device.move_to(value)
        status.wait(MOVE_TIMEOUT_S)
        return f"at {device.position:.3f} {device.units}"

    @staticmethod
    def _decode(frame: Frame, label: str) -> PreviewFrame:
        return PreviewFrame(make_preview(frame.data), label, frame.exposure_s, frame.iso,
                            frame.filename)

    @_while_attached
    def on_action_result(self, result: ActionResult) -> None:
        role = ROWS[result.key][0] if result.key else ""
        kind = {"estop": "estop", "session": "console", "open": "console",
                "preview": "camera"}.get(result.op, "device")
        if result.error is None:
            self.log_line(logging.INFO, kind, f"{result.op}: {result.text}", device=role or None)
            if role and result.op in ("connect", "home", "home_all"):
                self.devices_pane.clear_fault(role)
        else:
            msg = getattr(result.error, "message", str(result.error))
            self.log_line(logging.ERROR, kind, f"{result.op} failed: {result.error}",
                          device=role or None)
            self.notify(f"{role or 'console'}: {result.op} failed: {result.error}",
                        severity="error", timeout=8, markup=False)
            if role:
                self.devices_pane.set_fault(role, msg)
                if isinstance(result.error, Disconnected):
                    self.devices_pane.set_disconnected(role)
        self.poll_devices()

    @_while_attached
    async def on_frames_ready(self, message: FramesReady) -> None:
        self.last_frames = message.frames
        await self.preview_pane.show_bracket(message.frames)
        for frame in message.frames if message.test_shot else ():
            for warning in frame.preview.histogram.warnings():
                self.log_line(logging.WARNING, "camera", f"{frame.exposure_text}: {warning}",
                              device="camera")

    # -- store, plans, sessions ---------------------------------------------------------------
    @work(thread=True, exclusive=True, group="store")
    def open_store(self, plan_path: str | None = None) -> None:
        """Open the store (first call) and optionally a plan; post its steps and the sessions."""
        try:
            if self.store is None:
                self.store = backend.open_store(self.store_dir)
            steps, summary = None, ""
            if plan_path is not None:
                plan = backend.load_plan(plan_path)
                self.plan, self.plan_path = plan, str(plan_path)
                steps, summary = backend.plan_steps(plan, self.rig), backend.plan_summary(plan, self.rig)
            self.post_message(SessionLoaded(steps, summary, backend.session_rows(self.store)))
        except (OSError, ValueError, StoreError) as exc:
            self.post_message(ActionResult("open", "", "", exc))

    @_while_attached
    def on_session_loaded(self, message: SessionLoaded) -> None:
        if message.steps is not None:
            self.session_pane.show_plan(message.steps, message.summary, self.plan_path)
            self.log_line(logging.INFO, "console", message.summary)
        self.session_pane.show_sessions(message.sessions)

    def on_session_request(self, request: SessionRequest) -> None:
        op, pane = request.op, self.session_pane
        if op == "open":
            self.open_store(request.path)
        elif op in ("new", "resume_interrupted"):
            if self.runner_active or pane.state == "paused":
                self.notify("a session is open: resume (p) or abort (a) it first",
                            severity="warning", markup=False)
            elif self.rig is None or self.store is None:
                self.notify("the rig is not connected yet", severity="warning", markup=False)
            else:
                self._start_session(None if op == "new" else (request.name or ""))
        elif op == "process":
            if self.store is None or not request.name:
                self.notify("select a session in the sessions table first", severity="warning", markup=False)
            elif self.processing is not None:
                self.notify(f"already processing {self.processing}", severity="warning", markup=False)
            elif self.runner_active and self.runner is not None and self.session_pane.session_name == request.name:
                self.notify("the session is still being captured", severity="warning", markup=False)
            else:
                self.processing = request.name
                self.log_line(logging.INFO, "console", f"processing {request.name}")
                self._process(request.name)
        elif self.runner is None:
            self.notify("no session is open", severity="warning", markup=False)
        elif op == "pause" and self.runner_active:
            self.log_line(logging.INFO, "console", "pause requested (after the current step)")
            self.runner.request_pause()
        elif op == "resume" and not self.runner_active and pane.state == "paused":
            self._run_session(self.runner)
        elif op == "abort" and pane.state in ("running", "paused"):
            self.log_line(logging.WARNING, "console", "abort requested: stopping motion")
            self.runner.request_abort()
            if not self.runner_active:  # paused: let the runner record the abort itself
                self._run_session(self.runner)

    @work(thread=True, exclusive=True, group="store")
    def _start_session(self, resume: str | None) -> None:
        """Create a session from the open plan (``resume`` None) or resume a stored one, then run
        it (this worker becomes the runner's thread)."""
        options = {"prepare_target": backend.target_handler(
            self.opened, self._ask_target, prompt=self.prompt_targets), **self.runner_options}
        try:
            runner, steps, summary = backend.make_runner(
                self.rig, self.store, plan=self.plan, plan_path=self.plan_path, resume=resume,
                **options)
        except (ValueError, OSError, RigError, StoreError, RunnerError) as exc:
            self.post_message(ActionResult("session", "", "", exc))
            return
        self.post_message(SessionLoaded(steps, summary, backend.session_rows(self.store)))
        self.post_message(SessionOpened(runner))

    def _ask_target(self, target: str, step: Step) -> None:
        """The runner's ``prepare_target`` (runner thread): show the scene prompt and block
        until the operator answers. Cancelling raises, so the runner pauses before it moves."""
        self._target_reply.clear()

        def answered(ready: bool | None) -> None:
            self._target_ready = bool(ready)
            self._target_reply.set()
        self.call_from_thread(lambda: self.push_screen(TargetScreen(target, step.index, step_prompt(step)), answered))
        self._target_reply.wait()
        if not self._target_ready:
            raise TargetCancelled(f"the operator did not set up '{target}' for step {step.index}")

    @_while_attached
    def on_session_opened(self, message: SessionOpened) -> None:
        self.runner = message.runner
        self.action_show_tab("session")
        self._run_session(self.runner)

    def _run_session(self, runner: Any) -> None:
        self.runner_active = True
        self._runner_idle.clear()
        self.session_pane.state = "starting"
        self._runner_thread(runner)

    @work(thread=True, exclusive=True, group="runner")
    def _runner_thread(self, runner: Any) -> None:
        unsubscribe = runner.bus.subscribe(lambda ev: self.post_message(RunnerEvent(ev)))
        state, error = "paused", None
        try:
            state = runner.run()
        except Exception as exc:  # noqa: BLE001 - the runner has paused itself; show why
            error = exc
        finally:
            unsubscribe()
            self._runner_idle.set()
            self.post_message(SessionEnded(state, error))

    @_while_attached
    def on_session_ended(self, message: SessionEnded) -> None:
        self.runner_active = False
        if message.error is not None:
            self.log_line(logging.ERROR, "console", f"session stopped: {message.error}")
            self.notify(str(message.error), severity="error", timeout=10, markup=False)
        self.session_pane.state = message.state
        self.open_store()  # refresh the session list
        self.poll_devices()

    @work(thread=True, exclusive=True, group="process")
    def _process(self, session: str) -> None:
        """``gonio process`` on ``session`` (calibration if needed, every method, the report)."""
        def progress(p: backend.ProgressEvent) -> None:
            self.post_message(ProcessProgress(session, f"{p.stage} {p.part}".strip(), p.done, p.total))
        try:
            report = backend.process(self.store, session, progress=progress, **self.process_options)
        except Exception as exc:  # noqa: BLE001 - shown to the operator, the console goes on
            self.post_message(ProcessEnded(session, error=exc))
            return
        self.post_message(ProcessEnded(session, report))

    @_while_attached
    def on_process_progress(self, message: ProcessProgress) -> None:
        self.session_pane.show_processing(message.session, message.stage, message.done, message.total)

    @_while_attached
    def on_process_ended(self, message: ProcessEnded) -> None:
        self.processing = None
        if message.error is not None:
            self.log_line(logging.ERROR, "console", f"processing {message.session} failed: {message.error}")
            self.notify(f"processing {message.session} failed: {message.error}", severity="error",
                        timeout=15, markup=False)
            self.session_pane.show_processing(message.session, f"failed: {message.error}", 0, 0)
            return
        rep = message.report
        headline = backend.headline(rep)
        self.session_pane.show_processed(message.session, str(rep.report_path), headline)
        self.log_line(logging.INFO, "console", f"{message.session} processed: report {rep.report_path}")
        self.notify(f"report: {rep.report_path}", title=f"{message.session} processed", markup=False)

    @_while_attached
    def on_runner_event(self, message: RunnerEvent) -> None:
        event = message.event
        self.session_pane.apply_event(event)
        self.log_pane.add(LogEntry.from_event(event))
        kind = event.kind
        if kind == EventKind.FAULT:
            self.notify(f"{event.device or 'session'}: {event.message}", title="device fault",
                        severity="error", timeout=15, markup=False)
            if event.device:
                self.devices_pane.set_fault(event.device, event.message)
                if event.data.get("error") == "Disconnected":
                    self.devices_pane.set_disconnected(event.device)
        elif kind == EventKind.TARGET:
            self.notify(event.message, title="scene change", severity="warning", timeout=10, markup=False)
        elif kind == EventKind.MOVED:
            self.devices_pane.set_positions(event.data.get("positions", {}))
        elif kind == EventKind.FRAME_STORED and "sha256" in event.data:
            self._preview_step(event.session, event.step)
        elif kind in (EventKind.DONE, EventKind.ABORTED):
            self.notify(f"session {event.session}: {kind.value}", markup=False)

    @work(thread=True, exclusive=True, group="preview")
    def _preview_step(self, session: str, step: int) -> None:
        """Decode the frames of ``step`` stored so far (the bracket) for the Preview tab."""
        try:
            records = self.store.frames(self.store.session(session).id, step=step)
            frames = []
            for rec in records:
                with self._cache_lock:
                    cached = self._preview_cache.get(rec.sha256)
                if cached is None:
                    cached = make_preview(self.store.read_object(rec.sha256))
                    with self._cache_lock:
                        self._preview_cache[rec.sha256] = cached
                        while len(self._preview_cache) > 16:
                            self._preview_cache.pop(next(iter(self._preview_cache)))
                frames.append(PreviewFrame(cached, f"step {step} #{rec.bracket_index}",
                                           rec.exposure_s, rec.iso, rec.filename))
        except (OSError, PreviewError, StoreError) as exc:
            self.post_message(ActionResult("preview", "", "", exc))
            return
        self.post_message(FramesReady(frames))
