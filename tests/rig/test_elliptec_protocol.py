"""Elliptec protocol: pure codec and scripted byte exchanges (no port)."""
from __future__ import annotations

import threading

import pytest

from rig.elliptec import (STATUS, DeviceInfo, ElliptecRotator, encode_home, encode_info,
                          encode_move_absolute, encode_move_relative, encode_pulses, encode_request,
                          decode_pulses, parse_info, parse_position, parse_reply, parse_status,
                          status_error)
from rig.errors import (DeviceBusy, DeviceError, DeviceTimeout, LimitError, NotHomed,
                        ProtocolError)

IN_REPLY = b"0IN0E1140012320211501016800023000\r\n"


class Scripted:
    """A transport that checks each request against a script and plays back the replies."""

    def __init__(self, script: list[tuple[bytes, bytes | None]]) -> None:
        self.script = list(script)
        self.lock = threading.RLock()
        self.is_open = False
        self.pending = b""

    def open(self) -> None:
        self.is_open = True

    def close(self) -> None:
        self.is_open = False

    def reset_input(self) -> None:
        self.pending = b""

    def write(self, data: bytes) -> None:
        assert self.script, f"unexpected request {data!r}"
        expected, reply = self.script.pop(0)
        assert data == expected
        self.pending += reply or b""

    def read_until(self, terminator: bytes = b"\n", timeout_s: float | None = None) -> bytes:
        i = self.pending.find(terminator)
        if i < 0:
            raise DeviceTimeout("no reply", timeout_s=timeout_s)
        line, self.pending = self.pending[: i + len(terminator)], self.pending[i + len(terminator):]
        return line


def make(script, **kw) -> tuple[ElliptecRotator, Scripted]:
    t = Scripted([(b"0in", IN_REPLY), (b"0gs", b"0GS00\r\n")] + script)
    rot = ElliptecRotator("polarizer", "/dev/null", transport=t, **kw)
    rot.connect()
    return rot, t


def test_pulses_twos_complement_round_trip():
    assert encode_pulses(0) == "00000000"
    assert encode_pulses(35840) == "00008C00"
    assert encode_pulses(-15360) == "FFFFC400"
    assert encode_pulses(-1) == "FFFFFFFF"
    for p in (0, 1, -1, 143360, -143360, 2**31 - 1, -(2**31)):
        assert decode_pulses(encode_pulses(p)) == p
    with pytest.raises(ValueError, match="signed 32-bit"):
        encode_pulses(2**31)


def test_request_encoding_has_no_terminator():
    assert encode_move_absolute("0", 35840) == b"0ma00008C00"
    assert encode_move_relative("A", -15360) == b"AmrFFFFC400"
    assert encode_home("0") == b"0ho0" and encode_home("0", clockwise=False) == b"0ho1"
    assert encode_request("3", "gp") == b"3gp"
    with pytest.raises(ValueError, match="address"):
        encode_request("G", "gp")
    with pytest.raises(ValueError, match="command"):
        encode_request("0", "xx")
    with pytest.raises(ValueError, match="data characters"):
        encode_request("0", "ma", "123")


def test_in_reply_decoded_and_reencoded():
    info = parse_info(parse_reply(IN_REPLY))
    assert info == DeviceInfo(motor_type=14, serial_number="11400123", year="2021", firmware="15",
                              hardware_release=1, imperial_thread=False, travel=360,
                              pulses_per_unit=143360)
    assert encode_info(info) == IN_REPLY
    imperial = parse_info(parse_reply(b"0IN0E1140012320211581016800023000\r\n"))
    assert imperial.imperial_thread and imperial.hardware_release == 1


@pytest.mark.parametrize("raw", [b"0PO00008C00", b"0po00008C00\r\n", b"XPO00008C00\r\n",
                                 b"0P\r\n", b"\x85PO0\r\n"])
def test_malformed_replies_raise_protocol_error(raw):
    with pytest.raises(ProtocolError):
        parse_reply(raw)


def test_wrong_reply_kinds_raise_protocol_error():
    with pytest.raises(ProtocolError, match="PO"):
        parse_position(parse_reply(b"0GS00\r\n"))
    with pytest.raises(ProtocolError, match="GS"):
        parse_status(parse_reply(b"0GS0\r\n"))
    with pytest.raises(ProtocolError, match="IN"):
        parse_info(parse_reply(b"0IN0E11400\r\n"))
    with pytest.raises(ProtocolError, match="zero"):
        parse_info(parse_reply(b"0IN0E1140012320211501000000023000\r\n"))


@pytest.mark.parametrize("code", range(14))
def test_every_documented_status_maps_to_a_typed_error(code):
    reply = parse_reply(f"0GS{code:02X}\r\n".encode())
    assert parse_status(reply) == code
    err = status_error(code, device="polarizer")
    if code == 0:
        assert err is None
        return
    meaning = STATUS[code][0]
    assert meaning in str(err) and "polarizer" in str(err)
    expected = {1: DeviceTimeout, 9: DeviceBusy}.get(code, DeviceError)
    assert type(err) is expected
    if expected is DeviceError:
        assert err.code == code


def test_status_table_matches_manual():
    names = [STATUS[c][0] for c in range(14)]
    assert names[2] == "mechanical time out" and names[9] == "busy" and names[13].startswith("over current")
    assert "undocumented" in str(status_error(0x2A))


def test_connect_reads_info_and_describe_reports_it():
    rot, t = make([])
    d = rot.describe()
    assert d["model"] == "ELL14" and d["serial_number"] == "11400123"
    assert d["pulses_per_revolution"] == 143360 and rot.limits == (-360.0, 360.0)
    assert not t.script


def test_connect_refuses_other_module_types():
    t = Scripted([(b"0in", b"0IN0611400123202115010028000003E8\r\n")])
    with pytest.raises(DeviceError, match="type 6"):
        ElliptecRotator("polarizer", "/dev/null", transport=t).connect()


def test_pulses_per_rev_read_from_device_not_assumed():
    other = b"0IN0E1140012320211501016800010000\r\n"  # 65536 pulses/rev
    t = Scripted([(b"0in", other), (b"0gs", b"0GS00\r\n"), (b"0ho0", b"0PO00000000\r\n"),
                  (b"0ma00004000", b"0PO00004000\r\n")])
    rot = ElliptecRotator("polarizer", "/dev/null", transport=t)
    rot.connect()
    rot.home().wait(1)
    assert rot.move_to(90).wait(1) == pytest.approx(90.0)


def test_home_then_move_scripted():
    rot, t = make([(b"0ho0", b"0PO00000000\r\n"), (b"0ma00008C00", b"0PO00008C00\r\n"),
                   (b"0gp", b"0PO00008C00\r\n"), (b"0mrFFFFC400", b"0PO00005000\r\n")])
    with pytest.raises(NotHomed):
        rot.move_to(90)
    assert rot.home().wait(1) == 0.0 and rot.homed
    assert rot.move_to(90).wait(1) == pytest.approx(90.0)
    assert rot.position == pytest.approx(90.0)
    assert rot.move_by(-38.5714285).wait(1) == pytest.approx(20480 * 360 / 143360)
    assert not t.script


def test_negative_target_wraps_and_limits_checked():
    rot, t = make([(b"0ho0", b"0PO00000000\r\n"), (b"0ma0001EA00", b"0PO0001EA00\r\n")])
    rot.home().wait(1)
    assert rot.move_to(-45).wait(1) == pytest.approx(315.0)  # 0x1EA00 = 125440 pulses
    for bad in (361, -400, float("nan")):
        with pytest.raises(LimitError, match="outside the limits"):
            rot.move_to(bad)


def test_busy_is_retried_then_succeeds():
    rot, t = make([(b"0ho0", b"0GS09\r\n"), (b"0ho0", b"0GS09\r\n"), (b"0ho0", b"0PO00000000\r\n")])
    assert rot.home().wait(2) == 0.0
    assert not t.script


def test_busy_forever_raises_device_busy_within_bound():
    rot, t = make([(b"0gp", b"0GS09\r\n")] * 100, busy_retry_s=0.2)
    with pytest.raises(DeviceBusy, match="busy after 0.2 s"):
        rot.position


@pytest.mark.parametrize("code,err", [(2, DeviceError), (12, DeviceError), (13, DeviceError)])
def test_move_failure_status_raises_from_status(code, err):
    rot, t = make([(b"0ho0", b"0PO00000000\r\n"), (b"0ma00008C00", f"0GS{code:02X}\r\n".encode())])
    rot.home().wait(1)
    st = rot.move_to(90)
    with pytest.raises(err, match=STATUS[code][0]):
        st.wait(1)
    assert isinstance(st.exception(), err)


def test_reply_from_other_address_is_protocol_error():
    rot, t = make([(b"0gp", b"1PO00000000\r\n")])
    with pytest.raises(ProtocolError, match="address 1"):
        rot.position


def test_from_config_validates_keys():
    rot = ElliptecRotator.from_config("polarizer", {"driver": "elliptec", "port": "/dev/x",
                                                    "address": "2", "move_timeout_s": 3})
    assert rot.address == "2" and rot.move_timeout_s == 3
    with pytest.raises(ValueError, match=r"unknown key\(s\).*speed"):
        ElliptecRotator.from_config("polarizer", {"driver": "elliptec", "port": "x", "speed": 1})
    with pytest.raises(ValueError, match="timeout_s"):
        ElliptecRotator("p", "x", timeout_s=0)


def test_status_reply_in_place_of_data_raises_its_error():
    rot, t = make([(b"0gp", b"0GS0D\r\n")])
    with pytest.raises(DeviceError, match="over current") as info:
        rot.position
    assert info.value.code == 13
    t2 = Scripted([(b"0in", b"0GS03\r\n")])
    with pytest.raises(DeviceError, match="command error"):
        ElliptecRotator("polarizer", "/dev/null", transport=t2).connect()


def test_late_reply_after_timeout_is_discarded():
    rot, t = make([(b"0gp", None), (b"0gp", b"0PO00008C00\r\n")])
    with pytest.raises(DeviceTimeout):
        rot.position
    t.pending = b"0PO00004600\r\n"  # the first request's reply turns up late
    assert rot.position == pytest.approx(90.0)
