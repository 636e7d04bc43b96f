"""Rig files naming the zaber and grbl drivers: building, validation, and connecting to simulators."""
from __future__ import annotations

import pytest

from rig import ConfigError, LightTarget, Rig
from rig.grbl import GrblPositioner
from rig.kinematics import ArmKinematics, GantryKinematics
from rig.zaber import ZaberRotaryStage
from sims.grbl_sim import GrblSim
from sims.zaber_sim import ZaberSim


def test_rig_file_builds_drivers(tmp_path):
    path = tmp_path / "lab.toml"
    path.write_text('[rig]\nname = "bench"\n\n'
                    '[turntable]\ndriver = "zaber"\nport = "/dev/ttyUSB0"\ndevice = 2\n\n'
                    '[positioner]\ndriver = "grbl"\nport = "/dev/ttyACM0"\n'
                    'kinematics = { type = "gantry", origin_mm = [500, 500, 900], yaw_deg = 90.0 }\n')
    rig = Rig.from_config(path)
    assert isinstance(rig.turntable, ZaberRotaryStage) and rig.turntable.address == 2
    assert isinstance(rig.positioner, GrblPositioner)
    assert isinstance(rig.positioner.kinematics, GantryKinematics)
    assert rig.positioner.kinematics.origin_mm.tolist() == [500, 500, 900]


def test_default_kinematics_is_the_arm():
    rig = Rig.from_config({"positioner": {"driver": "grbl", "port": "/dev/ttyACM0", "kinematics": "arm"}})
    assert isinstance(rig.positioner.kinematics, ArmKinematics)


@pytest.mark.parametrize("section,match", [
    ({"driver": "grbl", "port": "/dev/x", "kinematics": "scara"}, r"\[positioner\].*scara"),
    ({"driver": "grbl", "port": "/dev/x", "feed": 3}, r"\[positioner\].*feed"),
    ({"driver": "grbl", "port": "/dev/x", "kinematics": {"type": "arm", "radius_mm": -1}},
     r"\[positioner\].*radius_mm"),
])
def test_bad_positioner_sections_are_config_errors(section, match):
    with pytest.raises(ConfigError, match=match):
        Rig.from_config({"positioner": section})


def test_bad_turntable_sections_are_config_errors():
    with pytest.raises(ConfigError, match=r"\[turntable\].*device"):
        Rig.from_config({"turntable": {"driver": "zaber", "port": "/dev/x", "device": 100}})


@pytest.mark.parametrize("role,section,match", [
    ("polarizer", {"driver": "elliptec", "port": "/dev/x", "address": "Z"}, r"\[polarizer\] address"),
    ("polarizer", {"driver": "elliptec", "port": "/dev/x", "move_timeout_s": -1}, r"\[polarizer\] move_timeout_s"),
    ("polarizer", {"driver": "elliptec", "port": "/dev/x", "timeout": 1}, r"\[polarizer\] unknown key\(s\).*timeout"),
    ("camera", {"driver": "ptp", "port": "usb:zz"}, r"\[camera\].*usb:VID:PID"),
    ("camera", {"driver": "ptp", "port": "usb:04a9:32b4", "exposure": 1}, r"\[camera\] unknown key\(s\).*exposure"),
    ("turntable", {"driver": "zaber", "port": "/dev/x", "speed": 9}, r"\[turntable\].*speed"),
])
def test_every_driver_reports_bad_sections_as_config_errors_naming_the_file(tmp_path, role, section, match):
    with pytest.raises(ConfigError, match=match):
        Rig.from_config({role: section})
    path = tmp_path / "bench.toml"
    path.write_text(f"[{role}]\n" + "".join(f"{k} = {v!r}\n".replace("'", '"') for k, v in section.items()))
    with pytest.raises(ConfigError, match=rf"{path}: .*{match}"):
        Rig.from_config(path)


@pytest.mark.parametrize("cfg,match", [
    ({"turntable": {"driver": "thorlabs", "port": "/dev/x"}}, r"driver = 'thorlabs' is unknown; known drivers: elliptec"),
    ({"turntable": {"driver": "zaber"}}, r"\[turntable\] needs a port"),
    ({"laser": {"driver": "zaber", "port": "/dev/x"}}, r"unknown section \[laser\]"),
    ({"turntable": {"driver": "zaber", "port": "sim"}}, r"start the simulators"),
    ({"turntable": {"driver": "ptp", "port": "usb:04a9:32b4"}}, r"driver 'ptp' cannot serve as the turntable \(it does not implement Axis\)"),
])
def test_unknown_drivers_sections_and_missing_ports(cfg, match):
    with pytest.raises(ConfigError, match=match):
        Rig.from_config(cfg)


def test_missing_and_malformed_rig_files(tmp_path):
    with pytest.raises(ConfigError, match="does not exist"):
        Rig.from_config(tmp_path / "none.toml")
    bad = tmp_path / "bad.toml"
    bad.write_text("[turntable\ndriver = 1\n")
    with pytest.raises(ConfigError, match="not valid TOML"):
        Rig.from_config(bad)
    binary = tmp_path / "photo.toml"  # a wrong file picked: was a bare UnicodeDecodeError
    binary.write_bytes(b"\xff\xd8\xff\xe0 JFIF")
    with pytest.raises(ConfigError, match="photo.toml: not a text file"):
        Rig.from_config(binary)


def test_rig_connects_to_simulators_and_moves():
    with ZaberSim(fast=True, homed=True) as zsim, GrblSim(fast=True, settings={22: 0}) as gsim:
        cfg = {"turntable": {"driver": "zaber", "port": zsim.port},
               "positioner": {"driver": "grbl", "port": gsim.port, "kinematics": "arm"}}
        with Rig.from_config(cfg) as rig:
            rig.turntable.move_to(33).wait(2)
            rig.positioner.move_to(LightTarget(azimuth_deg=10, elevation_deg=20)).wait(2)
            state = rig.read()
            assert state["turntable"]["angle"]["value"] == pytest.approx(33, abs=1e-3)
            assert state["positioner"]["light_position"]["value"] == pytest.approx(gsim.light_position_mm)
            assert rig.describe()["positioner"]["firmware"] == "Grbl 1.1h"
            rig.stop_all()
