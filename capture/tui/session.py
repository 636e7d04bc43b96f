"""The Session tab: plan, progress, current step, faults, and the sessions in the store.

Everything shown here comes from the runner's :class:`~capture.events.Event` stream (pushed down
by the app) and from read-only store queries; the pane posts :class:`SessionRequest` messages for
the app to act on.
"""
from __future__ import annotations

import time
from typing import Any

from rich.text import Text
from textual.app import ComposeResult
from textual.binding import Binding
from textual.containers import Horizontal, Vertical
from textual.message import Message
from textual.reactive import reactive
from textual.screen import ModalScreen
from textual.widgets import DataTable, Input, Label, ProgressBar, Static

from ..events import Event, EventKind
from ..plan import SCENE_TARGETS, Step
from ..store import StoredStep
from .devices import light_direction

#: store states a session can be resumed from ("running" in the store but not here: a crash)
RESUMABLE = ("running", "paused", "planned")


def fmt_duration(seconds: float | None) -> str:
    """``95`` -> ``1m35s``; ``None`` -> ``?``."""
    if seconds is None:
        return "?"
    s = int(round(max(seconds, 0.0)))
    h, rem = divmod(s, 3600)
    m, s = divmod(rem, 60)
    return f"{h}h{m:02d}m" if h else (f"{m}m{s:02d}s" if m else f"{s}s")


def fmt_bytes(n: float | None) -> str:
    if n is None:
        return "?"
    for unit in ("B", "kB", "MB", "GB"):
        if n < 1000 or unit == "GB":
            return f"{n:.0f} {unit}" if unit == "B" else f"{n:.1f} {unit}"
        n /= 1000
    return ""


def fmt_exposures(exposures: Any) -> str:
    if not exposures:
        return "-"
    vals = exposures if isinstance(exposures, (list, tuple)) else [exposures]
    return ", ".join(f"1/{1 / t:.0f}" if 0 < t < 0.5 else f"{t:g}" for t in vals) + " s"


def describe_step(step: Step) -> dict[str, str]:
    """Display columns of one plan step: turntable (deg), light (az/el deg or xyz mm),
    polarizer (deg), exposures (s)."""
    def deg(v: Any) -> str:
        return "-" if v is None else f"{v:g}°"

    light = step.light
    if light is None:
        light_s = "-"
    elif light.xyz_mm is not None:
        light_s = "({:g}, {:g}, {:g})".format(*light.xyz_mm)
    else:
        light_s = f"{light.azimuth_deg:g}/{light.elevation_deg:g}°"
    kind = step.kind or step.target or ""
    return {"turntable": deg(step.turntable_deg), "light": light_s, "polarizer": deg(step.polarizer_deg),
            "exposures": fmt_exposures(step.exposures_s), "kind": "" if kind in ("object", "measure") else str(kind)}


class SessionRequest(Message):
    """The operator asked for a session action: ``open`` (``path``), ``new``, ``pause``,
    ``resume``, ``abort``, ``resume_interrupted`` or ``process`` (``name``: the selected session
    or None)."""

    def __init__(self, op: str, *, path: str | None = None, name: str | None = None) -> None:
        super().__init__()
        self.op, self.path, self.name = op, path, name


class SessionPane(Vertical):
    """Plan summary, progress bar with ETA, current step, steps, sessions and faults."""

    BINDINGS = [
        Binding("o", "open_plan", "Open plan"),
        Binding("n", "request('new')", "New+start"),
        Binding("p", "toggle_pause", "Pause/resume"),
        Binding("a", "abort", "Abort (a a)"),
        Binding("r", "resume_interrupted", "Resume interrupted"),
        Binding("P", "process", "Process"),
    ]

    #: "idle", "running", "paused", "done", "aborted"
    state: reactive[str] = reactive("idle")

    def __init__(self, **kwargs) -> None:
        super().__init__(**kwargs)
        self.frames_stored = 0
        self.faults: list[tuple[Event, str]] = []
        self.session_name: str | None = None
        self._started = 0.0
        self._steps_at_start = 0
        self._step_data: dict[str, Any] = {}
        self._abort_armed = 0.0  # monotonic time of the first "a"

    def compose(self) -> ComposeResult:
        with Horizontal(id="plan-bar"):
            yield Input(placeholder="plan file (o to open)", id="plan-path")
            yield Label("idle", id="session-state")
        yield Static("no plan open", id="plan-summary")
        with Horizontal(id="progress-row"):
            yield ProgressBar(total=1, show_eta=False, id="progress")  # not None: no idle animation
            yield Label("", id="progress-text")
        yield Static("", id="current-step")
        yield Static("", id="processing")
        yield Static("", id="alert")
        with Horizontal(id="session-body"):
            steps = DataTable(id="steps", cursor_type="row", zebra_stripes=True)
            for key in ("#", "turntable", "light", "polarizer", "exposures", "kind", "status"):
                steps.add_column(key, key=key)
            yield steps
            with Vertical(id="session-side"):
                sessions = DataTable(id="sessions", cursor_type="row")
                for key in ("session", "state", "progress"):
                    sessions.add_column(key, key=key)
                yield sessions
                faults = DataTable(id="faults", cursor_type="row")
                for key in ("time", "device", "fault", "action"):
                    faults.add_column(key, key=key)
                yield faults

    def on_mount(self) -> None:
        self.query_one("#alert").display = False
        self.query_one("#processing").display = False

    # -- state in -----------------------------------------------------------------------------
    def show_plan(self, steps: list[StoredStep], summary: str, path: str | None = None) -> None:
        """Fill the steps table; ``path`` is the plan file, if any."""
        self.query_one("#plan-summary", Static).update(Text(summary))  # user text: no markup
        if path:
            self.query_one("#plan-path", Input).value = path
        table = self.query_one("#steps", DataTable)
        table.clear()
        for s in steps:
            cols = describe_step(s.step)
            table.add_row(str(s.index), cols["turntable"], cols["light"], cols["polarizer"],
                          cols["exposures"], cols["kind"], "done" if s.done else "", key=str(s.index))
        bar = self.query_one(ProgressBar)
        bar.update(total=max(len(steps), 1), progress=sum(s.done for s in steps))

    def show_sessions(self, rows: list[tuple[str, str, str]]) -> None:
        """``(name, state, "done/total")`` per session in the store, newest first."""
        table = self.query_one("#sessions", DataTable)
        table.clear()
        for name, state, progress in rows:
            style = {"running": "green", "paused": "yellow", "interrupted": "bold yellow",
                     "aborted": "red"}.get(state, "")
            table.add_row(Text(name), Text(state, style=style), progress, key=name)

    @property
    def selected_session(self) -> str | None:
        table = self.query_one("#sessions", DataTable)
        if table.row_count == 0:
            return None
        return str(table.coordinate_to_cell_key((table.cursor_row, 0)).row_key.value)

    def watch_state(self, state: str) -> None:
        styles = {"running": "bold green", "paused": "bold yellow", "aborted": "bold red",
                  "done": "bold cyan"}
        name = f"{self.session_name}: " if self.session_name else ""
        self.query_one("#session-state", Label).update(Text(name + state,
                                                            style=styles.get(state, "")))

    def apply_event(self, event: Event) -> None:  # noqa: C901 - one branch per event kind
        """Apply one runner event (called by the app on the UI thread)."""
        d = event.data
        kind = event.kind
        steps = self.query_one("#steps", DataTable)
        if kind in (EventKind.SESSION_STARTED, EventKind.RESUMED):
            self.session_name = event.session
            self.frames_stored = int(d.get("frames_done", 0))
            self._started = time.monotonic()
            self._steps_at_start = int(d.get("steps_done", 0))
            self.clear_alert()
            self.state = "running"
        elif kind == EventKind.STEP_STARTED and event.step is not None:
            self._step_data = dict(d)
            self._set_step_status(steps, event.step, Text("▶ running", style="bold green"))
            self.query_one("#current-step", Static).update(
                self._current_step_text(event.step, d))
        elif kind == EventKind.MOVED:
            # the read-back positions, with the step's exposures
            self.query_one("#current-step", Static).update(
                self._current_step_text(event.step, {**self._step_data, **d}))
        elif kind == EventKind.FRAME_STORED:
            self.frames_stored += 1
        elif kind == EventKind.STEP_DONE and event.step is not None:
            self._set_step_status(steps, event.step, "done")
        elif kind in (EventKind.FAULT, EventKind.RETRY):
            # what the runner did about it: a retry after a back-off, or a pause
            action = (f"retried ({d.get('attempt', '?')}, {d.get('delay_s', 0):g} s)"
                      if kind == EventKind.RETRY else "paused")
            self.add_fault(event, action)
        elif kind == EventKind.PAUSED:
            self.state = "paused"
            if event.device:  # paused by a device fault (an operator pause names no device)
                fault = next((f.message for f, _ in reversed(self.faults)
                              if f.kind == EventKind.FAULT), event.message)
                self.show_alert(f"⚠ PAUSED by a {event.device} fault: {fault}. Fix it, then "
                                "p to resume (Devices: c reconnects, h homes) or a to abort")
        elif kind == EventKind.DONE:
            self.state = "done"
        elif kind == EventKind.ABORTED:
            self.state = "aborted"
        self._update_progress(d)

    def _set_step_status(self, table: DataTable, step: int, value: Any) -> None:
        if str(step) in table.rows:
            table.update_cell(str(step), "status", value)
            table.move_cursor(row=table.get_row_index(str(step)))

    @staticmethod
    def _current_step_text(step: int | None, d: dict[str, Any]) -> Text:
        """Step, turntable (deg), light (az/el deg or xyz mm), polarizer (deg), exposures (s)
        from a step's plan dict and/or a ``positions`` read-back."""
        parts = [f"step {step}"]
        pos = d.get("positions", d)
        if pos.get("turntable_deg") is not None:
            parts.append(f"turntable {pos['turntable_deg']:.2f}°")
        light = pos.get("light")
        if "light_mm" in pos:  # a read-back: the light's position in the world frame, mm
            az, el, r = light_direction(pos["light_mm"])
            parts.append(f"light az {az:.1f}° el {el:.1f}° r {r:.0f} mm")
        elif isinstance(light, dict) and "azimuth_deg" in light:
            parts.append(f"light az {light['azimuth_deg']:.1f}° el {light['elevation_deg']:.1f}°")
        elif light is not None:
            parts.append(f"light {light}")
        if pos.get("polarizer_deg") is not None:
            parts.append(f"polarizer {pos['polarizer_deg']:.1f}°")
        if "exposures_s" in d:
            parts.append(f"exposures {fmt_exposures(d['exposures_s'])}")
        return Text(" · ".join(parts), style="bold")

    def _update_progress(self, d: dict[str, Any]) -> None:
        if "steps_total" not in d:
            return
        total, done = int(d["steps_total"]), int(d.get("steps_done", 0))
        bar = self.query_one(ProgressBar)
        bar.update(total=max(total, 1), progress=done if total else 1)
        eta = d.get("eta_s")
        if eta is None and done > self._steps_at_start and self._started:
            rate = (time.monotonic() - self._started) / (done - self._steps_at_start)
            eta = rate * (total - done)
        frames = f"{self.frames_stored}"
        if "frames_total" in d:
            frames += f"/{d['frames_total']}"
        self.query_one("#progress-text", Label).update(
            f"{done}/{total} steps · {frames} frames · ETA {fmt_duration(eta)}")

    def add_fault(self, event: Event, action: str) -> None:
        self.faults.append((event, action))
        table = self.query_one("#faults", DataTable)
        table.add_row(time.strftime("%H:%M:%S", time.localtime(event.time)), event.device or "",
                      Text(event.message, style="red"), action)
        table.move_cursor(row=table.row_count - 1)

    def show_processing(self, session: str, stage: str, done: int, total: int) -> None:
        """``gonio process`` progress of ``session``: the stage and how far it is."""
        box = self.query_one("#processing", Static)
        box.update(Text(f"processing {session}: {stage} {done}/{total}", style="bold"))
        box.display = True

    def show_processed(self, session: str, report: str, headline: list[tuple[str, str, str]]) -> None:
        """The finished processing: the report's path and per method ``(name, status, figure)``
        (the held-out relative RMS, or why it was skipped)."""
        lines = [f"{session} processed; report: {report}"]
        lines += [f"  {name}: {status} {figure}" for name, status, figure in headline]
        box = self.query_one("#processing", Static)
        box.update(Text("\n".join(lines)))
        box.display = True

    @property
    def processing_text(self) -> str | None:
        box = self.query_one("#processing", Static)
        return str(box.render()) if box.display else None

    def show_alert(self, message: str) -> None:
        alert = self.query_one("#alert", Static)
        alert.update(Text(message))
        alert.display = True

    def clear_alert(self) -> None:
        self.query_one("#alert", Static).display = False

    @property
    def alert_text(self) -> str | None:
        alert = self.query_one("#alert", Static)
        return str(alert.render()) if alert.display else None

    # -- actions out --------------------------------------------------------------------------
    def action_open_plan(self) -> None:
        box = self.query_one("#plan-path", Input)
        if box.value.strip():
            self.post_message(SessionRequest("open", path=box.value.strip()))
        else:
            box.focus()

    def on_input_submitted(self, event: Input.Submitted) -> None:
        event.stop()
        if event.value.strip():
            self.post_message(SessionRequest("open", path=event.value.strip()))
            self.query_one("#steps", DataTable).focus()

    def action_request(self, op: str) -> None:
        self.post_message(SessionRequest(op))

    def action_abort(self) -> None:
        """Abort needs ``a`` twice within 5 s: an aborted session is final (no resume)."""
        now = time.monotonic()
        if now - self._abort_armed <= 5.0:
            self._abort_armed = 0.0
            self.post_message(SessionRequest("abort"))
        else:
            self._abort_armed = now
            self.notify("press a again to abort the session (it cannot be resumed after)",
                        severity="warning", timeout=5)

    def action_toggle_pause(self) -> None:
        self.post_message(SessionRequest("resume" if self.state == "paused" else "pause"))

    def action_resume_interrupted(self) -> None:
        self.post_message(SessionRequest("resume_interrupted", name=self.selected_session))

    def action_process(self) -> None:
        self.post_message(SessionRequest("process", name=self.selected_session))


class TargetScreen(ModalScreen[bool]):
    """Asks the operator to set up the scene a step needs; dismissed with True (ready: the
    runner goes on) or False (cancelled: the session pauses before anything moves)."""

    BINDINGS = [Binding("enter", "dismiss(True)", "Ready"),
                Binding("escape", "dismiss(False)", "Cancel (pause)")]

    def __init__(self, target: str, step: int, prompt: str | None = None) -> None:
        super().__init__()
        self.target, self.step = target, step
        self.prompt = prompt or SCENE_TARGETS.get(target, "set up " + target)

    def compose(self) -> ComposeResult:
        with Vertical(id="target-box"):
            yield Label(Text(f"Step {self.step} needs: {self.target.replace('_', ' ')}",
                             style="bold"))
            yield Label(f"{self.prompt}, then press "
                        "enter. Escape pauses the session instead.")


