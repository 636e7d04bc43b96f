"""The link bookkeeping the three serial drivers share (``rig.transport.SerialDriver``): each
reports ``connected`` the same way and refuses commands with ``Disconnected`` naming itself
before ``connect()``, after ``close()`` and once its port has gone."""
from __future__ import annotations

import pytest

from rig import Disconnected, LightTarget
from rig.elliptec import ElliptecRotator
from rig.grbl import GrblPositioner
from rig.zaber import ZaberRotaryStage
from sims.elliptec_sim import ElliptecSim
from sims.grbl_sim import GrblSim
from sims.zaber_sim import ZaberSim

CASES = {
    "zaber": (lambda: ZaberSim(fast=True, homed=True), ZaberRotaryStage, 30.0),
    "grbl": (lambda: GrblSim(fast=True, settings={22: 0}), GrblPositioner,
             LightTarget(azimuth_deg=20, elevation_deg=10)),
    "elliptec": (lambda: ElliptecSim(name="polarizer", fast=True), ElliptecRotator, 30.0),
}


@pytest.mark.parametrize("kind", CASES)
def test_connected_close_and_refusal_are_the_same_for_every_serial_driver(kind):
    make_sim, driver_cls, target = CASES[kind]
    with make_sim() as sim:
        dev = driver_cls("dev", sim.port)
        assert not dev.connected
        with pytest.raises(Disconnected, match="connect\\(\\) first") as err:
            dev.move_to(target)
        assert err.value.device == "dev"
        dev.connect()
        assert dev.connected
        dev.transport.close()  # the port went away under the driver
        assert not dev.connected
        with pytest.raises(Disconnected):
            dev.move_to(target)
        dev.close()
        dev.close()  # safe twice
        assert not dev.connected
