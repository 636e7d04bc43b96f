"""User text through the CLI (issue 15): shown literally, never as rich markup; verify names the
step and frame of a bad file."""
from __future__ import annotations

import os
import sqlite3
import time

import pytest
from typer.testing import CliRunner

from capture.cli.session import app as session_app
from capture.plan import Plan
from capture.runner import create_session
from capture.store import Store

cli = CliRunner()
HOSTILE = "a [/bold] b [red]c[/red] [link=x]d \\[e]"


def _hostile_store(root):
    plan = Plan.from_dict({"name": "[bold]p", "object": HOSTILE, "operator": "[/]", "notes": "[i]",
                           "turntable": {"angles_deg": [0]}, "exposure": {"base_s": 0.01}})
    with Store(root) as st:
        sid = create_session(st, plan, None, name="ok", reserve_bytes=0).id
        st.add_frame(sid, 0, 0, 0, data=b"x" * 64, filename="[bold]IMG.DNG", format="dng",
                     exposure_requested_s=0.01, exposure_s=0.01, completes_step=True)
        create_session(st, plan, None, name="other", reserve_bytes=0)
    db = sqlite3.connect(root / "gonio.sqlite")  # a name from before names were checked
    db.execute("UPDATE sessions SET name = '[bold]n' WHERE name = 'other'")
    db.commit()
    db.close()


def test_markup_in_plans_and_names_is_shown_literally(tmp_path):
    _hostile_store(tmp_path / "st")
    r = cli.invoke(session_app, ["list", "--store", str(tmp_path / "st")])
    assert r.exit_code == 0, r.output
    text = "".join(r.output.split())
    assert "[bold]n" in text and "a[/bold]b" in text
    for name in ("ok", "[bold]n"):
        r = cli.invoke(session_app, ["show", name, "--store", str(tmp_path / "st")])
        assert r.exit_code == 0, r.output
        assert f"object {HOSTILE}" in r.output and "operator [/]" in r.output
        assert "notes: [i]" in r.output and name in r.output


def test_verify_names_the_step_and_frame_of_a_bad_file(tmp_path):
    _hostile_store(tmp_path / "st")
    with Store(tmp_path / "st") as st:
        f = st.frames(st.session("ok").id)[0]
        path = st.object_path(f.sha256)
    os.chmod(path, 0o644)
    path.write_bytes(b"y" * 64)
    r = cli.invoke(session_app, ["verify", "ok", "--store", str(tmp_path / "st")])
    assert r.exit_code == 1
    assert (f"corrupt: {f.sha256} (step 0 frame 0 of the bracket, repeat 0 ([bold]IMG.DNG))"
            in r.output)
    path.unlink()
    r = cli.invoke(session_app, ["verify", "ok", "--store", str(tmp_path / "st")])
    assert r.exit_code == 1 and f"missing: {f.sha256} (step 0 frame 0" in r.output


@pytest.mark.asyncio
async def test_the_console_shows_names_and_plan_text_literally(tmp_path):
    from textual.widgets import DataTable
    from textual.widgets._data_table import default_cell_formatter

    from capture.tui import GonioApp

    _hostile_store(tmp_path / "st")
    app = GonioApp("sim", tmp_path / "st", fast=True)
    app.animation_level = "none"
    async with app.run_test(size=(80, 24)) as pilot:
        await pilot.press("2")
        sessions = app.query_one("#sessions", DataTable)
        deadline = time.monotonic() + 30  # the list is read in a worker: slow on a loaded machine
        while sessions.row_count != 2 and time.monotonic() < deadline:
            await pilot.pause(0.05)
        # what the table draws: a plain str cell would be parsed as markup ("[bold]n" -> "n")
        shown = [default_cell_formatter(sessions.get_cell(key, "session")).plain
                 for key in ("ok", "[bold]n")]
        assert shown == ["ok", "[bold]n"]
        app.session_pane.show_plan([], f"{HOSTILE}: 1 steps")
        app.session_pane.show_alert("[/red] device said [bold]")
        await pilot.pause()
        assert str(app.query_one("#plan-summary").render()) == f"{HOSTILE}: 1 steps"
        assert app.session_pane.alert_text == "[/red] device said [bold]"
