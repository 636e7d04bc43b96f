"""SimLab: all four simulators, a rig config the drivers accept, and the physical state the camera
renders from."""
from __future__ import annotations

import pytest

from rig import LightTarget, Rig
from sims.lab import KINEMATICS, ROLES, SimLab
from sims.ptp_sim import placeholder_frame


def test_lab_serves_a_connectable_rig_and_reports_state():
    seen = []

    def frame_source(state):
        seen.append(dict(state))
        return placeholder_frame(state, size=(64, 48))

    with SimLab(fast=True, frame_source=frame_source) as lab:
        cfg = lab.rig_config()
        assert set(cfg) == {"rig", *ROLES}
        assert cfg["positioner"]["kinematics"] == KINEMATICS["arm"]
        assert cfg["camera"]["port"].startswith("usb:")
        with Rig.from_config(cfg, usb_backend=lab.usb_backend) as rig:
            rig.turntable.home().wait(2)
            rig.positioner.home().wait(2)
            rig.polarizer.home().wait(5)
            rig.turntable.move_to(72).wait(2)
            rig.positioner.move_to(LightTarget(azimuth_deg=30, elevation_deg=45)).wait(2)
            rig.polarizer.move_to(22.5).wait(5)
            state = lab.state()
            assert state["turntable_angle_deg"] == pytest.approx(72, abs=1e-3)
            assert state["light_position_mm"] == pytest.approx(rig.positioner.light_position_mm, abs=0.01)
            assert state["polarizer_angle_deg"] == pytest.approx(22.5, abs=0.01)
            frame = rig.camera.capture()
            assert frame.data[:4] in (b"II*\x00", b"MM\x00*")
        assert seen and seen[-1]["turntable_angle_deg"] == pytest.approx(72, abs=1e-3)
        assert seen[-1]["light_position_mm"] == pytest.approx(state["light_position_mm"])
    assert not lab.started and lab.sims == {}


def test_lab_subset_and_gantry():
    with SimLab(roles=("positioner",), kinematics="gantry") as lab:
        assert set(lab.sims) == {"positioner"} and lab.usb_backend is None
        assert lab.rig_config()["positioner"]["kinematics"]["type"] == "gantry"
        # powered up where its last homing left it: each axis at minus the pull-off ($27 = 1 mm)
        assert lab.state()["light_position_mm"] == pytest.approx((499.0, 499.0, 899.0))


def test_lab_rejects_bad_arguments():
    with pytest.raises(ValueError, match="kinematics"):
        SimLab(kinematics="hexapod")
    with pytest.raises(ValueError, match="role"):
        SimLab(roles=("laser",))
    with pytest.raises(ValueError, match="options"):
        SimLab(options={"laser": {}})
    with pytest.raises(RuntimeError, match="start"):
        SimLab().rig_config()


def test_lab_options_reach_the_simulators():
    with SimLab(roles=("turntable",), options={"turntable": {"speed_deg_s": 30.0, "homed": True}}) as lab:
        sim = lab.sims["turntable"]
        assert sim.speed * 360 / sim.cycle == pytest.approx(30.0, rel=1e-4)
        assert "WR" not in sim.flags


def test_fault_names_are_checked_per_simulator():
    with SimLab(fast=True, frame_source=lambda state: placeholder_frame(state, size=(64, 48))) as lab:
        documented = {"turntable": {"no_reply", "garble", "disconnect", "busy", "stall", "encoder", "limit"},
                      "positioner": {"no_reply", "garble", "disconnect", "alarm", "error"},
                      "polarizer": {"no_reply", "garble", "disconnect", "busy", "mechanical_timeout",
                                    "out_of_range"},
                      "camera": {"no_reply", "stall", "short_read", "corrupt_object", "disconnect"}}
        for role, names in documented.items():
            sim = lab.sims[role]
            for name in names - {"disconnect"}:
                sim.inject(name)  # accepted
            with pytest.raises(ValueError, match="unknown fault 'stal'"):
                sim.inject("stal")  # a typo arms nothing silently no more
        for role in documented:
            with pytest.raises(ValueError, match="count"):
                lab.sims[role].inject("no_reply", 0)
