"""Light-positioner kinematics: inverse/forward round trips, limits naming the axis, config, and the
simulator's copy of the forward maps (sims may not import rig) agreeing with rig's."""
from __future__ import annotations

import numpy as np
import pytest

from rig import LightTarget, LimitError
from rig.kinematics import ArmKinematics, GantryKinematics, MachineMap, kinematics_from_config
from sims.grbl_sim import light_position_mm as sim_forward
from sims.lab import KINEMATICS


def test_arm_direction_round_trip():
    kin = ArmKinematics(radius_mm=600, centre_mm=(10, -5, 50))
    rng = np.random.default_rng(0)
    for az, el in zip(rng.uniform(-180, 180, 50), rng.uniform(0, 85, 50)):
        m = kin.inverse(LightTarget(azimuth_deg=az, elevation_deg=el))
        assert m == pytest.approx({"X": az, "Y": el})
        p = np.array(kin.forward(m)) - (10, -5, 50)
        assert np.linalg.norm(p) == pytest.approx(600)
        assert np.degrees(np.arctan2(p[1], p[0])) == pytest.approx(az)
        assert np.degrees(np.arcsin(p[2] / 600)) == pytest.approx(el)


def test_arm_point_target_and_wrap():
    kin = ArmKinematics(radius_mm=500)
    m = kin.inverse(LightTarget(xyz_mm=(0.0, -500.0, 0.0)))
    assert m == pytest.approx({"X": -90.0, "Y": 0.0})
    assert kin.inverse(LightTarget(azimuth_deg=350, elevation_deg=10))["X"] == pytest.approx(-10)
    assert kin.inverse(LightTarget(azimuth_deg=-540, elevation_deg=10))["X"] == pytest.approx(-180)


def test_arm_limits_name_the_axis():
    kin = ArmKinematics(radius_mm=500, azimuth_limits_deg=(-90, 90), elevation_limits_deg=(0, 85))
    with pytest.raises(LimitError, match=r"elevation \(machine axis Y\) 86 deg is outside the limits 0..85 deg"):
        kin.inverse(LightTarget(azimuth_deg=0, elevation_deg=86))
    with pytest.raises(LimitError, match=r"azimuth \(machine axis X\) 135 deg is outside the limits -90..90"):
        kin.inverse(LightTarget(azimuth_deg=135, elevation_deg=10))
    with pytest.raises(LimitError, match="distance"):
        kin.inverse(LightTarget(azimuth_deg=0, elevation_deg=10, distance_mm=450))
    with pytest.raises(LimitError, match="distance of the point"):
        kin.inverse(LightTarget(xyz_mm=(0, 0, 100)))
    err = pytest.raises(LimitError, kin.inverse, LightTarget(azimuth_deg=0, elevation_deg=-5)).value
    assert err.limits == (0.0, 85.0) and err.unit == "deg" and err.value == -5


def test_gantry_round_trip_with_rotation_and_limits():
    kin = GantryKinematics(origin_mm=(500, 500, 900), yaw_deg=30,
                           travel_mm={"X": (-1000, 0), "Y": (-1000, 0), "Z": (-1000, 0)})
    p = (100.0, -50.0, 300.0)
    m = kin.inverse(LightTarget(xyz_mm=p))
    assert kin.forward(m) == pytest.approx(p)
    d = kin.inverse(LightTarget(azimuth_deg=0, elevation_deg=90, distance_mm=200))
    assert kin.forward(d) == pytest.approx((0, 0, 200), abs=1e-9)
    with pytest.raises(LimitError, match="machine axis Z"):
        kin.inverse(LightTarget(xyz_mm=(0, 0, 950)))


def test_bad_parameters_are_named():
    with pytest.raises(ValueError, match="radius_mm"):
        ArmKinematics(radius_mm=0)
    with pytest.raises(ValueError, match="centre_mm"):
        ArmKinematics(centre_mm=(0, 0))
    with pytest.raises(ValueError, match="elevation_limits_deg"):
        ArmKinematics(elevation_limits_deg=(10, 5))
    for beyond_the_pole in ((0, 95), (-100, 45), (-100, 95)):
        with pytest.raises(ValueError, match=r"elevation_limits_deg must lie in \[-90, 90\]"):
            ArmKinematics(elevation_limits_deg=beyond_the_pole)
    with pytest.raises(ValueError, match="orthonormal"):
        GantryKinematics(rotation=[[2, 0, 0], [0, 1, 0], [0, 0, 1]])
    with pytest.raises(ValueError, match="travel_mm"):
        GantryKinematics(travel_mm={"X": (0, 1)})
    with pytest.raises(ValueError, match="unknown"):
        kinematics_from_config("scara")
    with pytest.raises(ValueError, match="arm"):
        kinematics_from_config({"type": "arm", "wingspan": 3})


@pytest.mark.parametrize("table", [KINEMATICS["arm"], KINEMATICS["gantry"],
                                   {"type": "arm", "radius_mm": 321.0, "centre_mm": [5, 6, 7]},
                                   {"type": "gantry", "origin_mm": [1, 2, 3], "yaw_deg": 37.0,
                                    "travel_mm": {"X": [-500, 0], "Y": [-500, 0], "Z": [-500, 0]}}])
def test_sim_forward_kinematics_matches_rig(table):
    kin = kinematics_from_config(table)
    rebuilt = kinematics_from_config(kin.to_config())
    rng = np.random.default_rng(1)
    for m in rng.uniform(-90, 0, size=(20, 3)):
        machine = dict(zip("XYZ", m))
        assert sim_forward(table, m) == pytest.approx(kin.forward(machine), abs=1e-9)
        assert rebuilt.forward(machine) == pytest.approx(kin.forward(machine), abs=1e-9)


@pytest.mark.parametrize("kwargs,match", [
    (dict(azimuth_deg=float("nan"), elevation_deg=10), "azimuth_deg must be a finite number"),
    (dict(azimuth_deg=10, elevation_deg=float("inf")), "elevation_deg must be a finite number"),
    (dict(azimuth_deg=10, elevation_deg=10, distance_mm=0), "distance_mm must be > 0"),
    (dict(azimuth_deg=10, elevation_deg=10, distance_mm=float("nan")), "distance_mm must be a finite"),
    (dict(xyz_mm=(1.0, 2.0)), "xyz_mm must be 3 finite numbers"),
    (dict(xyz_mm=(1.0, 2.0, float("nan"))), "xyz_mm must be 3 finite numbers"),
    (dict(azimuth_deg=10), "either azimuth_deg and elevation_deg, or xyz_mm"),
])
def test_light_target_rejects_non_finite_and_incomplete_values(kwargs, match):
    # a NaN compares False with every limit: it must be stopped before it can reach the G-code
    with pytest.raises(ValueError, match=match):
        LightTarget(**kwargs)
    assert LightTarget(azimuth_deg=np.int64(30), elevation_deg=np.float32(12.5)).azimuth_deg == 30


def test_sim_machine_map_matches_rig():
    """sims/grbl_sim.py repeats the machine map (sims may not import rig): same light position."""
    table = {"machine_offset": {"X": -181.0, "Y": -94.0}, "machine_sign": {"Y": -1}}
    m = MachineMap.from_config(table["machine_offset"], table["machine_sign"])
    kin = kinematics_from_config(KINEMATICS["arm"])
    for machine in [(-181.0, -94.0, -1.0), (-361.0, -150.0, 0.0), (-1.0, -40.5, -1.0)]:
        expected = kin.forward(m.to_axes(dict(zip("XYZ", machine))))
        assert sim_forward(KINEMATICS["arm"], machine, table) == pytest.approx(expected, abs=1e-9)
