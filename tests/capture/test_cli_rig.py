"""``gonio rig`` commands and ``capture.rigs.open_rig`` against the simulated lab."""
from __future__ import annotations

import json
import shutil
import subprocess
import tomllib

import pytest
from typer.testing import CliRunner

from capture.cli import app
from capture.rigs import open_rig, to_toml
from rig import Disconnected, LightTarget
from rig.rig import load_config

runner = CliRunner()


def test_check_sim_prints_every_device():
    result = runner.invoke(app, ["rig", "check", "--rig", "sim"])
    assert result.exit_code == 0, result.output
    for text in ("turntable", "positioner", "polarizer", "camera", "zaber", "grbl", "Grbl 1.1h",
                 " deg", " mm", "usb:"):
        assert text in result.output


def test_check_json():
    result = runner.invoke(app, ["rig", "check", "--rig", "sim", "--json"])
    assert result.exit_code == 0, result.output
    rows = {r["role"]: r for r in json.loads(result.output)}
    assert set(rows) == {"turntable", "positioner", "polarizer", "camera"}
    assert all(r["ok"] for r in rows.values())
    assert rows["turntable"]["position"].endswith("deg") and rows["turntable"]["homed"] is False
    assert rows["positioner"]["firmware"] == "Grbl 1.1h"


def test_check_reports_failing_device_and_exits_1(tmp_path):
    path = tmp_path / "rig.toml"
    path.write_text('[turntable]\ndriver = "zaber"\nport = "sim"\n\n'
                    f'[positioner]\ndriver = "grbl"\nport = "{tmp_path / "no-such-port"}"\n')
    result = runner.invoke(app, ["rig", "check", "--rig", str(path)])
    assert result.exit_code == 1
    assert "FAILED" in result.output and "positioner" in result.output
    assert "1 of 2 device(s) failed" in result.output and "cannot open" in result.output


def test_check_missing_file_is_a_clear_error(tmp_path):
    result = runner.invoke(app, ["rig", "check", "--rig", str(tmp_path / "nope.toml")])
    assert result.exit_code == 2
    assert "does not exist" in result.output


def test_home_sim():
    result = runner.invoke(app, ["rig", "home", "--rig", "sim"])
    assert result.exit_code == 0, result.output
    assert result.output.count("homed at") == 3  # turntable, positioner, polarizer
    result = runner.invoke(app, ["rig", "home", "--rig", "sim", "--role", "laser"])
    assert result.exit_code == 2 and "laser" in result.output


def test_sim_prints_and_writes_a_usable_rig_file(tmp_path):
    out = tmp_path / "sim.toml"
    result = runner.invoke(app, ["rig", "sim", "--fast", "--duration", "0.2", "--write", str(out)])
    assert result.exit_code == 0, result.output
    cfg = tomllib.loads(out.read_text())
    load_config(cfg)
    assert {"turntable", "positioner", "polarizer"} <= set(cfg) and "camera" not in cfg
    assert cfg["positioner"]["kinematics"]["type"] == "arm"
    assert cfg["turntable"]["port"] in result.output


def test_open_rig_homes_and_closes_the_lab():
    with open_rig("sim", home=True) as opened:
        assert opened.rig.turntable.homed and opened.rig.positioner.homed
        opened.rig.positioner.move_to(LightTarget(azimuth_deg=10, elevation_deg=10)).wait(2)
        lab = opened.lab
    assert not lab.started


def test_open_rig_failure_stops_simulators(tmp_path):
    cfg = {"turntable": {"driver": "zaber", "port": "sim"},
           "positioner": {"driver": "grbl", "port": str(tmp_path / "absent")}}
    with pytest.raises(Disconnected):
        open_rig(cfg)


def test_to_toml_round_trip():
    cfg = {"rig": {"name": "x", "fast": True},
           "positioner": {"driver": "grbl", "port": "/dev/a", "kinematics": {"type": "arm", "centre_mm": [0.0, 1, 2]}}}
    assert tomllib.loads(to_toml(cfg)) == cfg


@pytest.mark.skipif(shutil.which("gonio") is None, reason="console script not installed")
def test_readme_command():
    proc = subprocess.run(["gonio", "rig", "check", "--rig", "sim"], capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stderr
    assert "positioner" in proc.stdout


def test_rig_file_from_running_sim_is_usable_while_it_serves(tmp_path):
    import threading
    import time

    from rig import Rig

    out = tmp_path / "live.toml"
    worker = threading.Thread(target=runner.invoke,
                              args=(app, ["rig", "sim", "--fast", "--duration", "2", "--write", str(out)]))
    worker.start()
    try:
        deadline = time.monotonic() + 10
        while not out.exists() and time.monotonic() < deadline:
            time.sleep(0.02)
        with Rig.from_config(out) as rig:  # as another process would
            rig.turntable.home().wait(2)
            assert rig.turntable.move_to(45).wait(2) == pytest.approx(45.0, abs=1e-3)
            assert rig.positioner.describe()["firmware"] == "Grbl 1.1h"
    finally:
        worker.join(10)
