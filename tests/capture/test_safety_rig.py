"""Rig files, simulator folders, Ctrl-C (issue 15): each rig-file mistake is named by file,
section and key; a simulated rig leaves no temporary folder; a quick second Ctrl-C exits 3."""
from __future__ import annotations

import os
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import pytest
from typer.testing import CliRunner

from capture.cli.capture import app as capture_app
from capture.cli.rig import app as rig_app
from capture.rigs import open_rig, to_toml
from capture.store import Store
from capture_fakes import tolerant_sim_config
from rig.errors import DeviceTimeout
from sims.lab import SimLab

cli = CliRunner()
PLAN = """
name = "slow"
[turntable]
angles_deg = { start = 0, stop = 315, step = 45 }
[light]
azimuth_deg = [0]
elevation_deg = [40]
[exposure]
base_s = 0.01
"""


@pytest.mark.parametrize("text, words", [
    ('[turntable]\ndriver = "zaber"\nport = 5\n', ["[turntable] port = 5 must be a text"]),
    ('[turntable]\ndriver = "zaber"\nport = "/dev/ttyUSB0"\nbaudrate = "fast"\n',
     ["[turntable] baudrate = 'fast' must be a whole number"]),
    ('[polarizer]\ndriver = "elliptec"\nport = "/dev/ttyUSB0"\ntimeout_s = "1"\n',
     ["[polarizer] timeout_s = '1' must be a number"]),
    ('[turntable]\ndriver = "zaber"\nport = "/dev/ttyUSB0"\n[polarizer]\ndriver = "elliptec"\n'
     'port = "/dev/ttyUSB0"\n', ["[polarizer] port = '/dev/ttyUSB0' is the same device as the "
                                  "[turntable] port"]),
    ('[turntable]\ndriver = "zaber"\nport = "/dev/ttyUSB0"\n[polarizer]\ndriver = "elliptec"\n'
     'port = "/dev/./ttyUSB0"\n', ["[polarizer] port = '/dev/./ttyUSB0' is the same device as the "
                                    "[turntable] port = '/dev/ttyUSB0'"]),
    ('[turntable]\ndriver = "zaber"\nport = "/dev/ttyUSB0"\ntimeout_s = inf\n',
     ["[turntable] timeout_s = inf must be a finite number"]),
    ('[turntable]\ndriver = "zaber"\nport = "/dev/ttyUSB0"\ntimeout_s = nan\n',
     ["[turntable] timeout_s = nan must be a finite number"]),
    ('[positioner]\ndriver = "grbl"\nport = "/dev/ttyUSB0"\nbaudrate = -5\n',
     ["[positioner] baudrate = -5 must be greater than 0"]),
    ('[turntable]\ndriver = "zaber"\nport = "/dev/ttyUSB0"\npoll_retries = -1\n',
     ["[turntable] poll_retries = -1 must be 0 or more"]),
    ('[turntable]\ndriver = ["zaber"]\nport = "/dev/ttyUSB0"\n',
     ["[turntable] driver = ['zaber'] is unknown"]),
    ('[camera]\ndriver = "zaber"\nport = "sim"\n',
     ["[camera] driver = 'zaber' with port = 'sim'", "speaks the 'ptp' protocol"]),
    ('[turntable]\ndriver = "grbl"\nport = "sim"\n',
     ["[turntable] driver = 'grbl' with port = 'sim'", "'zaber'"]),
], ids=["port-int", "baudrate-text", "timeout-text", "same-port", "same-port-spelled-twice",
        "timeout-inf", "timeout-nan", "baudrate-negative", "retries-negative", "driver-list",
        "zaber-as-camera", "grbl-as-turntable"])
def test_rig_file_mistakes_are_named_by_file_section_and_key(tmp_path, text, words):
    rig = tmp_path / "lab.toml"
    rig.write_text(text)
    r = cli.invoke(rig_app, ["check", "--rig", str(rig)])
    out = " ".join(r.output.split())
    assert r.exit_code == 2, out
    assert str(rig) in out and all(w in out for w in words), out
    assert "rig config" not in out  # the file's name, in the inner message too
    assert "cable" not in out and "Traceback" not in out


def test_a_timeout_is_printed_to_the_millisecond():
    assert "within 1 s" in str(DeviceTimeout("no reply", timeout_s=1 - 1e-7))
    assert "within 0.25 s" in str(DeviceTimeout("no reply", timeout_s=0.2500004))


@pytest.fixture
def private_tmp(tmp_path, monkeypatch):
    """tempfile's folder for this test only (other tests start simulators in /tmp meanwhile)."""
    t = tmp_path / "tmp"
    t.mkdir()
    monkeypatch.setattr(tempfile, "tempdir", str(t))
    return t


def test_simulated_rig_commands_leave_no_temporary_folder(tmp_path, private_tmp):
    r = cli.invoke(rig_app, ["check", "--rig", "sim"])
    assert r.exit_code == 0, r.output
    rig = tmp_path / "rig.toml"  # one sim role, then a failure while opening the rest
    rig.write_text('[turntable]\ndriver = "zaber"\nport = "sim"\n[camera]\ndriver = "ptp"\n'
                   'port = "usb:1:2"\ntimeout_s = -1\n')
    assert cli.invoke(rig_app, ["check", "--rig", str(rig)]).exit_code == 2
    with pytest.raises(TypeError):  # a simulator that cannot be built: the started ones clean up
        SimLab(roles=["turntable", "positioner"], options={"positioner": {"bogus": 1}}).start()
    opened = open_rig("sim")
    assert len(list(private_tmp.iterdir())) == 3  # the three serial simulators' ports
    opened.close()
    assert list(private_tmp.iterdir()) == []


def test_a_second_ctrl_c_soon_after_the_first_stops_and_exits_3(tmp_path):
    plan, rig = tmp_path / "plan.toml", tmp_path / "rig.toml"
    plan.write_text(PLAN)
    rig.write_text(to_toml(tolerant_sim_config()))
    private = tmp_path / "tmp"
    private.mkdir()
    p = subprocess.Popen([sys.executable, "-m", "capture.cli", "capture", "run", str(plan), "--rig",
                          str(rig), "--store", str(tmp_path / "st"), "--session", "c", "--quiet"],
                         stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                         env={**os.environ, "TMPDIR": str(private), "PYTHONUNBUFFERED": "1"})
    seen = []
    for line in p.stderr:
        seen.append(line)
        if line.startswith("target: put the object"):
            break
    p.send_signal(signal.SIGINT)
    time.sleep(0.1)
    p.send_signal(signal.SIGINT)  # while the step is captured, or while the rig is being closed
    said = []
    for line in p.stdout:
        said.append(line)
        if "paused; continue with" in line:
            break
    p.send_signal(signal.SIGINT)  # and a third while gonio closes the rig and the store
    out, err = p.communicate(timeout=120)
    out, err = "".join(said) + out, "".join(seen) + err
    assert p.returncode == 3, out + err
    assert "pausing after the current step" in err
    assert "Traceback" not in err
    with Store(tmp_path / "st") as st:
        assert st.session("c").state == "paused"
    assert list(private.iterdir()) == []  # Ctrl-C too leaves no simulator folder


def test_sigterm_during_a_simulated_capture_pauses_it_and_leaves_no_folder(tmp_path):
    plan, private = tmp_path / "plan.toml", tmp_path / "tmp"
    plan.write_text(PLAN)
    private.mkdir()
    p = subprocess.Popen([sys.executable, "-m", "capture.cli", "capture", "run", str(plan), "--rig",
                          "sim", "--store", str(tmp_path / "st"), "--session", "t", "--quiet"],
                         stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                         env={**os.environ, "TMPDIR": str(private), "PYTHONUNBUFFERED": "1"})
    said = []
    for line in p.stdout:
        said.append(line)
        if line.startswith("session t:"):  # the session is recorded and about to run
            break
    assert len(list(private.glob("gonio-sim-*"))) == 3  # the simulators are up
    p.send_signal(signal.SIGTERM)
    out, err = p.communicate(timeout=120)
    out = "".join(said) + out
    assert p.returncode == 3 and "paused; continue with" in out, out + err
    assert f"gonio capture resume t --rig sim --store {tmp_path / 'st'}" in out  # not '<rig>'
    assert "Traceback" not in err
    with Store(tmp_path / "st") as st:
        assert st.session("t").state == "paused" and st.progress(st.session("t").id).steps_done < 8
    assert list(private.iterdir()) == []
