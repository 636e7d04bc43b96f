"""``gonio tui``: option checking (the app itself is covered by test_tui.py)."""
from __future__ import annotations

from typer.testing import CliRunner

from capture.cli import app

runner = CliRunner()


def test_tui_help_lists_the_options():
    result = runner.invoke(app, ["tui", "--help"])
    assert result.exit_code == 0
    for option in ("--rig", "--store", "--plan", "--fast", "--poll"):
        assert option in result.output


def _text(output: str) -> str:
    """The error panel's words on one line (rich wraps them in a box)."""
    return " ".join(output.replace("│", " ").split())


def test_tui_rejects_a_missing_plan_and_a_bad_poll_period(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    result = runner.invoke(app, ["tui", "--store", "s", "--plan", "nope.toml"])
    assert result.exit_code == 2
    assert "plan file nope.toml does not exist" in _text(result.output)
    result = runner.invoke(app, ["tui", "--store", "s", "--poll", "0"])
    assert result.exit_code == 2
    assert "must be > 0 seconds and at most 60, got 0.0" in _text(result.output)
    assert not (tmp_path / "s").exists()  # nothing was opened
