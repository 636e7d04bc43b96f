"""ZaberSim against Zaber's own client library (``zaber-motion``, PyPI; a ``test`` extra).

The simulator was written from the ASCII protocol manual by the same hands as ``rig/zaber.py``;
here code that Zaber wrote drives it over the same pseudo-terminal a real stage would sit behind:
device detection, the identification queries, generic commands, home, moves, stop, warnings and
alerts.

Full identification (``Device.identify()``) also looks the device id up in Zaber's device
database, which the library fetches from Zaber's web service or reads from a downloaded file.
Neither is reachable here, so the test points the library at a database file that does not exist
and checks that identification gets as far as that look-up with every device query answered the
way a real stage answers it; the units conversions that need the database are not exercised.

Evidence from the library (zaber-motion 10.3), recorded here because the real library is right
where it disagrees with the simulator:

- ``detect_devices`` sends ``/0 0 00`` then ``/1 0 01 get comm.packet.size.max`` (with a checksum);
- ``identify()`` sends, in order, ``get deviceid``, ``get system.serial``, ``get version``,
  ``get version.build``, ``get device.hw.modified``, ``get comm.command.packets.max``,
  ``get comm.word.size.max``, ``get get.settings.max``, ``get system.axiscount`` (device scope),
  then ``get resolution`` and ``get peripheralid`` on axis 1;
- with ``get.settings.max`` answered (12 on firmware 7.38), ``settings.get_many`` and
  ``get_synchronized`` send one ``/1 0 get 1 maxspeed pos`` (axis number, then the settings in
  alphabetical order) and split the reply's data on ``;``: to ``629146 0`` (values separated by
  spaces) zaber-motion 10.3's Go core answered ``panic: runtime error: index out of range [1]
  with length 1`` in ``runSyncBatch`` and aborted the Python process; to ``629146 ; 0`` it
  returns both values.
"""
from __future__ import annotations

import pytest

zaber_motion = pytest.importorskip("zaber_motion", reason="zaber-motion (test extra) not installed")

from zaber_motion import DeviceDbSourceType, Library, Units  # noqa: E402
from zaber_motion.ascii import Connection, GetAxisSetting, GetSetting  # noqa: E402
from zaber_motion.exceptions import (BadCommandException, DeviceDbFailedException,  # noqa: E402
                                     MovementFailedException)

from sims.zaber_sim import ZaberSim  # noqa: E402

REQUEST_TIMEOUT_MS = 1000  # the library's per-request reply timeout
DETECT_TIMEOUT_MS = 300  # the simulator answers within milliseconds


@pytest.fixture(scope="module")
def no_device_db():
    """Point the library at a device database that is not there (no network either), so that
    identification fails at the look-up every time, not depending on what the machine can reach."""
    Library.set_device_db_source(DeviceDbSourceType.FILE, "/nonexistent/zaber-devices.sqlite")
    yield
    Library.set_device_db_source(DeviceDbSourceType.WEB_SERVICE)  # the library's default again


@pytest.fixture(scope="module")
def chain(no_device_db):
    """(simulator, connection, device 1) with the moves timed as on the real stage."""
    sim = ZaberSim(fast=False, speed_deg_s=360.0, accel_deg_s2=3600.0)
    port = sim.start()
    conn = Connection.open_serial_port(port)
    try:
        # detection listens for answers to its broadcast for one request timeout: keep it short
        conn.default_request_timeout = DETECT_TIMEOUT_MS
        devices = conn.detect_devices(identify_devices=False)
        conn.default_request_timeout = REQUEST_TIMEOUT_MS
        assert len(devices) == 1
        yield sim, conn, devices[0]
    finally:
        conn.close()
        sim.stop()


def _requests(sim, since: int) -> list[bytes]:
    """Requests the library sent since index ``since``, checksum stripped."""
    return [r.rsplit(b":", 1)[0] if b":" in r else r for r in sim.requests[since:]]


def _without_id(request: bytes) -> bytes:
    """``/1 0 07 get pos`` -> ``/1 0 get pos`` (the message id counts up per request)."""
    words = request.split(b" ")
    return b" ".join(words[:2] + words[3:])


def test_detection_finds_the_stage_at_its_address(chain):
    sim, _, device = chain
    assert device.device_address == 1
    # the broadcast probe and the packet-size query came first, as the library sends them
    assert _requests(sim, 0)[:2] == [b"/0 0 00", b"/1 0 01 get comm.packet.size.max"]
    reply = device.generic_command("get comm.packet.size.max")
    assert (reply.reply_flag, reply.data) == ("OK", "80")


def test_identification_queries_are_answered_until_the_device_database(chain):
    sim, _, device = chain
    start = len(sim.requests)
    with pytest.raises(DeviceDbFailedException, match="Device Database"):
        device.identify()
    sent = [_without_id(r)[5:] for r in _requests(sim, start)]  # without "/1 0 " / "/1 1 "
    assert sent == [b"get deviceid", b"get system.serial", b"get version", b"get version.build",
                    b"get device.hw.modified", b"get comm.command.packets.max",
                    b"get comm.word.size.max", b"get get.settings.max", b"get system.axiscount",
                    b"get resolution", b"get peripheralid"]
    # the same queries through the library's generic command path: the device answers each
    expected = {"deviceid": "50419", "version": "7.38", "version.build": "15708",
                "device.hw.modified": "0", "comm.command.packets.max": "5",
                "comm.word.size.max": "50", "get.settings.max": "12", "system.axiscount": "1",
                "system.access": "1"}
    for setting, value in expected.items():
        reply = device.generic_command(f"get {setting}")
        assert (reply.reply_flag, reply.data) == ("OK", value), setting
    # an integrated stage has no peripheral: the axis rejects the query, as on the device
    reply = device.generic_command("get peripheralid", axis=1, check_errors=False)
    assert (reply.reply_flag, reply.data) == ("RJ", "BADCOMMAND")


def test_generic_commands_echo_and_settings(chain):
    sim, _, device = chain
    assert device.generic_command("tools echo gonio 42").data == "gonio 42"
    axis = device.get_axis(1)
    start = len(sim.requests)
    results = axis.settings.get_many(GetAxisSetting("maxspeed"), GetAxisSetting("resolution"))
    # maxspeed in Zaber data units: 360 deg/s x 1,536,000 microsteps/rev / 360 x 1.6384
    maxspeed = round(360 * 1_536_000 / 360 * 1.6384)
    assert [(r.setting, r.value) for r in results] == [("maxspeed", maxspeed), ("resolution", 64.0)]
    synced = axis.settings.get_synchronized(GetAxisSetting("pos"), GetAxisSetting("accel"))
    assert [r.value for r in synced] == [sim._counter(), sim.settings["accel"]]
    # one multi-setting get each, not one get per setting
    assert [_without_id(r) for r in _requests(sim, start)] == [b"/1 0 get 1 maxspeed resolution",
                                                            b"/1 0 get 1 accel pos"]
    device_values = device.settings.get_many(GetSetting("version.build"), GetSetting("system.axiscount"))
    assert [r.values for r in device_values] == [[15708.0], [1.0]]
    assert axis.settings.get("limit.cycle.dist") == 1_536_000


def test_home_then_moves_and_alerts_through_the_vendor_library(chain):
    sim, conn, device = chain
    axis = device.get_axis(1)
    device.generic_command("system reset")  # power-up state: no reference position
    assert "WR" in axis.warnings.get_flags()
    with pytest.raises(BadCommandException):  # absolute moves need a reference, as on the stage
        axis.move_absolute(1000, Units.NATIVE)
    axis.home()
    assert "WR" not in axis.warnings.get_flags()
    alerts = []
    subscription = conn.alert.subscribe(alerts.append)
    try:
        device.generic_command("set comm.alert 1")
        axis.move_absolute(384_000, Units.NATIVE)  # 90 deg, waits for IDLE by polling
        assert axis.get_position(Units.NATIVE) == 384_000
        assert sim.angle_deg == pytest.approx(90.0, abs=1e-6)
        axis.move_relative(-128_000, Units.NATIVE)  # -30 deg
        assert axis.get_position(Units.NATIVE) == 256_000
    finally:
        device.generic_command("set comm.alert 0")
        subscription.dispose()
    # the alert for the end of each move reached the library's alert stream
    assert [(a.device_address, a.axis_number, a.status) for a in alerts] == [(1, 1, "IDLE")] * 2


def test_stop_mid_move_and_a_stall_warning(chain):
    sim, _, device = chain
    axis = device.get_axis(1)
    axis.home()
    axis.move_relative(768_000, Units.NATIVE, wait_until_idle=False)  # half a turn, ~0.6 s
    assert axis.is_busy()
    axis.stop()  # decelerates, then waits until idle
    stopped = axis.get_position(Units.NATIVE)
    assert 0 < stopped < 768_000 and not sim.busy
    sim.inject("stall")
    with pytest.raises(MovementFailedException, match="FS"):
        axis.move_relative(100_000, Units.NATIVE)
    # the library cleared the fault after reporting it; the position is where the stall left it
    assert axis.get_position(Units.NATIVE) == pytest.approx(stopped + 50_000, abs=1)
