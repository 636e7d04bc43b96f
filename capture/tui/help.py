"""The help screen: every key of the console, by tab."""
from __future__ import annotations

from textual.app import ComposeResult
from textual.binding import Binding
from textual.containers import VerticalScroll
from textual.screen import ModalScreen
from textual.widgets import Markdown

HELP = """\
# gonio operator console

**Anywhere**

| key | action |
| --- | --- |
| `ctrl+e` / `F12` | **EMERGENCY STOP**: stop every axis at once and pause the session |
| `1` `2` `3` `4` | Devices, Session, Preview, Log tab |
| `F1` / `?` | this help (close with `F1`, `?`, `q` or `escape`) |
| `ctrl+q` | quit (a running session is paused and the devices are stopped first) |

**Devices** (select an axis with the arrow keys)

| key | action |
| --- | --- |
| `-` / `+` | jog the selected axis down / up by the step size |
| `[` / `]` | smaller / larger jog step (0.1, 1, 5, 10, 45) |
| `g` | go to: type a position (deg or mm) and press enter |
| `h` | home the selected axis (the positioner homes all its axes) |
| `H` | home every axis and the positioner at once |
| `s` | stop the selected axis |
| `c` | reconnect the selected device (after a cable was pulled), or open the rig |
| `e` / `i` | set exposure (s) / ISO of the camera |
| `t` | test shot: capture with the current settings and show it in Preview |

**Session**

| key | action |
| --- | --- |
| `o` | open a plan file (TOML) and show its steps, duration and data size |
| `n` | new session from the open plan, and start it |
| `p` | pause / resume the running session |
| `a` `a` | abort the session: `a` twice within 5 s (motion stops; the steps done stay in the store, but an aborted session cannot be resumed) |
| `r` | resume the interrupted session selected in the list (or the latest one) |
| `P` | process the selected session: calibration if needed, every method, the HTML report; progress, the report's path and each method's held-out error appear below the progress bar |

**Preview** shows the last frame (2x2-binned raw, sRGB) and one histogram per exposure of the
bracket, with the percentage of pixels clipped at the white level or crushed at the black level.
`+` / `-` change the display gain.

**Log** lists the runner's events and the console's actions; filter by level, kind and text.
"""


class HelpScreen(ModalScreen[None]):
    """Modal help; any of the listed keys closes it."""

    BINDINGS = [Binding("escape,q,f1,question_mark", "dismiss", "Close help")]

    def compose(self) -> ComposeResult:
        with VerticalScroll(id="help-box"):
            yield Markdown(HELP)
