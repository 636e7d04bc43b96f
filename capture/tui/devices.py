"""The Devices tab: state of every device, jog / go-to / home / stop per axis, camera settings.

The pane only shows state and posts :class:`DeviceRequest` messages; the app does the device I/O
on worker threads and pushes new :class:`DeviceState` rows down (attributes down, messages up).
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

from rich.text import Text
from textual.app import ComposeResult
from textual.binding import Binding
from textual.containers import Horizontal, Vertical
from textual.message import Message
from textual.reactive import reactive
from textual.widgets import DataTable, Input, Label

from rig.device import Axis, Camera, Device, LightPositioner

#: jog step sizes, in the selected axis' units (deg or mm)
JOG_STEPS = (0.1, 1.0, 5.0, 10.0, 45.0)

#: table rows: key -> (device role, sub-axis of the positioner or None)
ROWS = {"turntable": ("turntable", None), "positioner.az": ("positioner", "az"),
        "positioner.el": ("positioner", "el"), "polarizer": ("polarizer", None),
        "camera": ("camera", None)}
_COLUMNS = (("device", "Device"), ("position", "Position"), ("state", "State"),
            ("homed", "Homed"), ("link", "Link"), ("fault", "Last fault"),
            ("model", "Model / firmware"))


@dataclass(frozen=True)
class DeviceState:
    """What the console knows about one table row (an axis, or the camera).

    Attributes
    ----------
    key : str
        Row key (see :data:`ROWS`).
    connected : bool
    model : str
        Model and firmware, as the device describes itself.
    value : float or None
        Numeric position in ``units`` (degrees / millimetres), for jogging.
    units : str
    text : str
        Position (or camera settings) formatted for display.
    homed : bool or None
    busy : bool or None
    state : str
        The controller's own state when it is not plain idle (``Alarm``, ``Hold:0`` ...).
    """

    key: str
    connected: bool
    model: str = ""
    value: float | None = None
    units: str = ""
    text: str = ""
    homed: bool | None = None
    busy: bool | None = None
    state: str = ""


def light_direction(xyz_mm: tuple[float, float, float]) -> tuple[float, float, float]:
    """Azimuth (deg, from +x towards +y), elevation (deg above the platter plane) and distance
    (mm) of a point in the world (turntable) frame."""
    x, y, z = xyz_mm
    return (math.degrees(math.atan2(y, x)), math.degrees(math.atan2(z, math.hypot(x, y))),
            math.sqrt(x * x + y * y + z * z))


def _model(info: dict[str, Any]) -> str:
    model = str(info.get("model") or info.get("driver") or "?")
    fw = info.get("firmware")
    return f"{model} fw {fw}" if fw else model


def _value(readings: dict[str, dict[str, Any]], *names: str) -> Any:
    """The first of ``names`` present in a ``read()`` result, or None."""
    return next((readings[n]["value"] for n in names if n in readings), None)


#: controller states that mean "moving" (GRBL Run/Jog/Home, Elliptec "busy")
_MOVING = {"run", "jog", "home", "homing", "busy", "moving"}


def _state(readings: dict[str, dict[str, Any]]) -> tuple[bool | None, str]:
    """``(busy, state text)`` from a read(): a ``busy`` flag, or a controller state text."""
    flag = _value(readings, "busy", "moving")
    text = _value(readings, "state", "status")
    if text is None:
        return (None if flag is None else bool(flag)), ""
    word = str(text).split(":")[0].split(",")[0].strip().lower()
    busy = bool(flag) if flag is not None else word in _MOVING
    return busy, "" if word in ("idle", "ok") else str(text)


def snapshot(role: str, device: Device, info: dict[str, Any]) -> list[DeviceState]:
    """Query one device (blocking I/O: call from a worker) and return its table rows.

    ``info`` is its cached ``describe()``. Raises the device's typed error if it does not answer.
    """
    model = _model(info)
    readings = device.read()
    busy, state = _state(readings)
    homed = _value(readings, "homed")
    if isinstance(device, LightPositioner):
        xyz = _value(readings, "light_position")
        xyz = tuple(device.light_position_mm if xyz is None else xyz)
        az, el, r = light_direction(xyz)
        homed = device.homed if homed is None else bool(homed)
        return [DeviceState("positioner.az", True, model, az, "deg", f"az {az:.2f}° r {r:.0f} mm",
                            homed, busy, state),
                DeviceState("positioner.el", True, "", el, "deg",
                            "el {:.2f}° ({:.0f}, {:.0f}, {:.0f}) mm".format(el, *xyz), homed,
                            busy, state)]
    if isinstance(device, Camera):
        exposure = _value(readings, "exposure_s")
        iso = _value(readings, "iso")
        exposure = device.exposure_s if exposure is None else exposure
        text = f"{exposure:g} s" + (f"  ISO {iso:g}" if iso else "")
        return [DeviceState(role, True, model, None, "", text, None, busy, state)]
    assert isinstance(device, Axis)
    pos = next((r["value"] for r in readings.values() if r.get("units") == device.units
                and isinstance(r["value"], (int, float))), None)
    pos = device.position if pos is None else pos
    homed = device.homed if homed is None else bool(homed)
    return [DeviceState(role, True, model, float(pos), device.units,
                        f"{pos:.3f} {device.units}", homed, busy, state)]


class DeviceRequest(Message):
    """The operator asked for something on a device.

    ``op`` is one of ``jog`` (``value`` = signed step), ``goto`` (``value`` = target),
    ``home``, ``home_all``, ``stop``, ``exposure`` (seconds), ``iso``, ``test_shot``,
    ``connect`` (reconnect the device, or open the rig); ``key`` is the table row (see
    :data:`ROWS`; empty for ``home_all``).
    """

    def __init__(self, op: str, key: str = "", value: float | None = None) -> None:
        super().__init__()
        self.op, self.key, self.value = op, key, value


class DevicesPane(Vertical):
    """Device table with jog controls and camera settings."""

    BINDINGS = [
        Binding("minus", "jog(-1)", "Jog-"),
        Binding("plus,equals_sign", "jog(1)", "Jog+", key_display="+"),
        Binding("left_square_bracket", "step(-1)", "Step -", show=False),
        Binding("right_square_bracket", "step(1)", "Step +", show=False),
        Binding("g", "focus_input('goto')", "Go to"),
        Binding("h", "request('home')", "Home"),
        Binding("H", "request('home_all')", "Home all", show=False),
        Binding("s", "request('stop')", "Stop"),
        Binding("t", "request('test_shot')", "Shot"),
        Binding("e", "focus_input('exposure')", "Exposure", show=False),
        Binding("i", "focus_input('iso')", "ISO", show=False),
        Binding("c", "request('connect')", "Reconnect", show=False),
    ]

    step_index: reactive[int] = reactive(1)

    def __init__(self, **kwargs) -> None:
        super().__init__(**kwargs)
        self.states: dict[str, DeviceState] = {}
        self.faults: dict[str, str] = {}

    def compose(self) -> ComposeResult:
        table = DataTable(id="device-table", cursor_type="row", zebra_stripes=True)
        for key, label in _COLUMNS:
            table.add_column(label, key=key)
        yield table
        with Horizontal(id="jog-bar"):
            yield Label("", id="jog-step")
            yield Input(placeholder="go to (g)", id="goto", type="number")
            yield Input(placeholder="exposure s (e)", id="exposure", type="number")
            yield Input(placeholder="ISO (i)", id="iso", type="number")

    def on_mount(self) -> None:
        table = self.query_one(DataTable)
        for key, (role, axis) in ROWS.items():
            table.add_row(role if axis is None else f"{role} {axis}", "", "", "", "-", "", "",
                          key=key)
        self.watch_step_index(self.step_index)

    # -- state in -----------------------------------------------------------------------------
    @property
    def selected(self) -> str:
        """Row key under the cursor."""
        table = self.query_one(DataTable)
        return list(ROWS)[table.cursor_row]

    @property
    def jog_step(self) -> float:
        return JOG_STEPS[self.step_index]

    def set_absent(self, key: str) -> None:
        """The rig has no such device."""
        self._update(key, link=Text("not fitted", style="dim"))

    def set_state(self, state: DeviceState) -> None:
        self.states[state.key] = state
        link = Text("connected", style="green") if state.connected else Text("lost", style="bold red")
        homed = "" if state.homed is None else ("yes" if state.homed else Text("NO", style="yellow"))
        if state.busy:
            busy = Text(state.state or "BUSY", style="bold cyan")
        elif state.state:
            busy = Text(state.state, style="bold yellow")
        else:
            busy = "" if state.busy is None else "idle"
        self._update(state.key, link=link, model=state.model, position=state.text, homed=homed,
                     state=busy)

    def set_positions(self, positions: dict[str, Any]) -> None:
        """Positions read back by the runner (``turntable_deg``, ``light_mm``, ``polarizer_deg``)
        while a session runs and the console does not poll."""
        for key in ("turntable", "polarizer"):
            if f"{key}_deg" in positions:
                self._update(key, position=f"{positions[f'{key}_deg']:.3f} deg")
        if "light_mm" in positions:
            az, el, r = light_direction(positions["light_mm"])
            self._update("positioner.az", position=f"az {az:.2f}° r {r:.0f} mm")
            self._update("positioner.el", position=f"el {el:.2f}°")

    def set_busy(self, key: str, busy: bool) -> None:
        self._update(key, state=Text("BUSY", style="bold cyan") if busy else "idle")

    def set_fault(self, role: str, message: str) -> None:
        """Record the last fault of a device (shown on all of its rows)."""
        self.faults[role] = message
        for key, (r, _) in ROWS.items():
            if r == role:
                self._update(key, fault=Text(message, style="red"))

    def clear_fault(self, role: str) -> None:
        self.faults.pop(role, None)
        for key, (r, _) in ROWS.items():
            if r == role:
                self._update(key, fault="")

    def set_disconnected(self, role: str) -> None:
        for key, (r, _) in ROWS.items():
            if r == role:
                self._update(key, link=Text("lost", style="bold red"), state="")

    def _update(self, key: str, **cells: Any) -> None:
        table = self.query_one(DataTable)
        for column, value in cells.items():
            if table.get_cell(key, column) != value:  # polling repeats values: skip the redraw
                table.update_cell(key, column, value, update_width=True)

    def watch_step_index(self, index: int) -> None:
        if self.is_mounted:
            self.query_one("#jog-step", Label).update(
                f"jog step [b]{JOG_STEPS[index]:g}[/b] ([ ] to change)")

    # -- actions out --------------------------------------------------------------------------
    def action_step(self, direction: int) -> None:
        self.step_index = min(max(self.step_index + direction, 0), len(JOG_STEPS) - 1)

    def action_jog(self, sign: int) -> None:
        if self.selected == "camera":
            self.notify("the camera has no axis to jog", severity="warning", markup=False)
            return
        self.post_message(DeviceRequest("jog", self.selected, sign * self.jog_step))

    def action_request(self, op: str) -> None:
        key = {"test_shot": "camera", "home_all": ""}.get(op, self.selected)
        self.post_message(DeviceRequest(op, key))

    def action_focus_input(self, which: str) -> None:
        self.query_one(f"#{which}", Input).focus()

    def on_input_submitted(self, event: Input.Submitted) -> None:
        event.stop()
        which = event.input.id
        try:
            value = float(event.value)
        except ValueError:
            self.notify(f"{which}: {event.value!r} is not a number", severity="error", markup=False)
            return
        key = self.selected if which == "goto" else "camera"
        op = {"goto": "goto", "exposure": "exposure", "iso": "iso"}[which]
        self.post_message(DeviceRequest(op, key, value))
        event.input.value = ""
        self.query_one(DataTable).focus()
