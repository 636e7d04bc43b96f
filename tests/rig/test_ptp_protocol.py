"""PTP codec, datasets and PtpSession against scripted USB transfers (no device)."""
from __future__ import annotations

import array
import errno
import struct
import time

import pytest
import usb.core

from rig.errors import DeviceBusy, DeviceError, DeviceTimeout, Disconnected, ProtocolError
from rig.ptp import (ContainerType, DataType, Event, Op, Prop, PtpError, PtpSession, Reader, Resp,
                     decode_container, encode_container, pack_string, pack_value,
                     parse_device_info, parse_object_info, parse_prop_desc)

OUT, IN, EVT = 0x01, 0x82, 0x83


def cmd(op, tid, *params):
    return struct.pack(f"<IHHI{len(params)}I", 12 + 4 * len(params), 1, op, tid, *params)


def resp(code, tid, *params):
    return struct.pack(f"<IHHI{len(params)}I", 12 + 4 * len(params), 3, code, tid, *params)


def data(op, tid, payload):
    return struct.pack("<IHHI", 12 + len(payload), 2, op, tid) + payload


def ucs2(text):  # independent of rig.ptp.pack_string
    return bytes([len(text) + 1]) + text.encode("utf-16-le") + b"\0\0" if text else b"\0"


class ScriptedUsb:
    """Plays a list of expected transfers: ('w', bytes), ('r', bytes | exception), ('e', ...)."""

    def __init__(self, script):
        self.script = list(script)
        self.cleared = []
        self.control = []

    def write(self, ep, payload, timeout):
        kind, expected = self.script.pop(0)
        assert (kind, ep) == ("w", OUT), f"host wrote {bytes(payload)!r}, script expected {kind}"
        assert bytes(payload) == expected
        return len(payload)

    def read(self, ep, buf, timeout):
        kind, reply = self.script.pop(0)
        assert ep == (IN if kind == "r" else EVT), f"host read endpoint 0x{ep:02x}, script has {kind}"
        if isinstance(reply, Exception):
            raise reply
        assert len(reply) <= len(buf), "reply longer than the host's buffer"
        buf[:len(reply)] = type(buf)("B", reply)
        return len(reply)

    def clear_halt(self, ep):
        self.cleared.append(ep)

    def ctrl_transfer(self, bm_request_type, b_request, w_value, w_index, data_or_length, timeout):
        self.control.append((bm_request_type, b_request, w_index, bytes(data_or_length)
                             if b_request == 0x64 else data_or_length))
        if b_request == 0x67:  # Get Device Status: OK
            return array.array("B", struct.pack("<HH", 4, 0x2001))
        return len(data_or_length)


def session(script, **kw) -> tuple[PtpSession, ScriptedUsb]:
    dev = ScriptedUsb(script)
    kw.setdefault("timeout_s", 0.2)
    return PtpSession(dev, ep_out=OUT, ep_in=IN, ep_event=EVT, **kw), dev


def opened(script, **kw):
    s, dev = session([("w", cmd(0x1002, 0, 1)), ("r", resp(0x2001, 0))] + script, **kw)
    s.open(1)
    return s, dev


# -- containers -------------------------------------------------------------------------------
def test_command_container_bytes_match_the_standard():
    assert encode_container(ContainerType.COMMAND, Op.OpenSession, 0, (1,)) == \
        bytes.fromhex("10000000 0100 0210 00000000 01000000")
    assert encode_container(ContainerType.RESPONSE, Resp.OK, 7) == bytes.fromhex("0c000000 0300 0120 07000000")


@pytest.mark.parametrize("ctype,params,payload", [(1, (1, 2, 3, 4, 5), b""), (2, (), b"\x00" * 1000),
                                                  (3, (0xFFFFFFFF,), b""), (4, (), b"")])
def test_container_round_trip(ctype, params, payload):
    raw = encode_container(ctype, 0x1234, 99, params, payload)
    c = decode_container(raw)
    assert (c.type, c.code, c.transaction_id, c.params, c.payload) == (ctype, 0x1234, 99, params, payload)
    assert struct.unpack_from("<I", raw)[0] == len(raw)


def test_container_errors():
    with pytest.raises(ValueError, match="at most 5"):
        encode_container(1, 0x1001, 1, (0,) * 6)
    with pytest.raises(ValueError, match="uint32"):
        encode_container(1, 0x1001, 1, (-1,))
    with pytest.raises(ProtocolError, match="shorter"):
        decode_container(b"\x0c\x00\x00")
    with pytest.raises(ProtocolError, match="length field 16"):
        decode_container(resp(0x2001, 1, 5)[:14] + b"\0\0" + b"\0\0\0\0" )
    with pytest.raises(ProtocolError, match="type 9"):
        decode_container(struct.pack("<IHHI", 12, 9, 0x2001, 1))
    with pytest.raises(ProtocolError, match="parameter block"):
        decode_container(struct.pack("<IHHI", 14, 3, 0x2001, 1) + b"\0\0")


# -- datasets ---------------------------------------------------------------------------------
def test_strings_round_trip_ucs2():
    for text in ("", "Canon Inc.", "Größe 5µm", "IMG_0001.DNG"):
        packed = pack_string(text)
        assert packed == ucs2(text)
        assert Reader(packed).string() == text
    with pytest.raises(ProtocolError, match="ends early"):
        Reader(ucs2("Nikon")[:-3]).string()


def test_device_info_parsed():
    raw = (struct.pack("<HIH", 100, 0x0B, 200) + ucs2("microsoft.com: 1.0") + struct.pack("<H", 0)
           + struct.pack("<I3H", 3, 0x1001, 0x100E, 0x1009) + struct.pack("<I2H", 2, 0x4002, 0x400D)
           + struct.pack("<I1H", 1, 0x500D) + struct.pack("<I", 0) + struct.pack("<I2H", 2, 0x3801, 0x3811)
           + ucs2("Nikon Corporation") + ucs2("D850") + ucs2("V1.10") + ucs2("6012345"))
    info = parse_device_info(raw)
    assert info.standard_version == 100 and info.vendor_extension_id == 0x0B
    assert info.vendor_extension_desc == "microsoft.com: 1.0"
    assert info.operations == (0x1001, 0x100E, 0x1009) and info.events == (0x4002, 0x400D)
    assert info.properties == (0x500D,) and info.capture_formats == () and info.image_formats == (0x3801, 0x3811)
    assert (info.manufacturer, info.model, info.device_version, info.serial_number) == \
        ("Nikon Corporation", "D850", "V1.10", "6012345")
    with pytest.raises(ProtocolError, match="DeviceInfo ends early"):
        parse_device_info(raw[:-5])


def test_prop_desc_enum_and_range():
    enum = (struct.pack("<HHB", 0x500D, 6, 1) + struct.pack("<II", 100, 167) + b"\x02"
            + struct.pack("<H3I", 3, 10, 100, 167))
    d = parse_prop_desc(enum)
    assert (d.code, d.datatype, d.writable, d.factory_default, d.current, d.form, d.values) == \
        (0x500D, DataType.UINT32, True, 100, 167, "enum", (10, 100, 167))
    rng = struct.pack("<HHB", 0x500F, 4, 0) + struct.pack("<HH", 100, 400) + b"\x01" + struct.pack("<HHH", 100, 6400, 100)
    d = parse_prop_desc(rng)
    assert (d.form, d.minimum, d.maximum, d.step, d.writable, d.current) == ("range", 100, 6400, 100, False, 400)
    with pytest.raises(ProtocolError, match="form flag 7"):
        parse_prop_desc(rng[:9] + b"\x07")


def test_pack_value_types():
    assert pack_value(DataType.UINT32, 167) == b"\xa7\x00\x00\x00"
    assert pack_value(DataType.UINT16, 400) == b"\x90\x01"
    assert pack_value(DataType.STR, "ab") == ucs2("ab")
    with pytest.raises(ValueError, match="does not fit"):
        pack_value(DataType.UINT16, 70000)


def test_object_info_parsed():
    raw = (struct.pack("<IHHIHIIIIIIIHII", 0x10001, 0x3811, 0, 48_000_000, 0x3801, 5000, 160, 120,
                       6000, 4000, 16, 0, 0, 0, 7) + ucs2("DSC_0042.DNG") + ucs2("20261121T101500")
           + ucs2("") + ucs2(""))
    info = parse_object_info(raw)
    assert info.compressed_size == 48_000_000 and info.filename == "DSC_0042.DNG"
    assert (info.image_width, info.image_height, info.image_bit_depth) == (6000, 4000, 16)
    assert info.format_name == "dng" and info.capture_date == "20261121T101500"
    # vendor raw formats as libgphoto2's ptp.h numbers them (CRW 0xB101, CRW3 = CR2 0xB103, CR3 0xB108)
    for code, name in ((0xB103, "cr2"), (0xB108, "cr3"), (0x3801, "jpeg"), (0xB999, "0xB999")):
        assert parse_object_info(raw[:4] + struct.pack("<H", code) + raw[6:]).format_name == name


# -- session: scripted exchanges --------------------------------------------------------------
def test_open_session_then_transaction_ids_count_from_one():
    s, dev = opened([("w", cmd(0x1015, 1, 0x500D)), ("r", data(0x1015, 1, struct.pack("<I", 167))),
                     ("r", resp(0x2001, 1)), ("w", cmd(0x1015, 2, 0x500F)),
                     ("r", data(0x1015, 2, struct.pack("<H", 400))), ("r", resp(0x2001, 2))])
    assert s.get_prop_value(Prop.ExposureTime, DataType.UINT32) == 167
    assert s.get_prop_value(Prop.ExposureIndex, DataType.UINT16) == 400
    assert not dev.script


def test_device_info_outside_a_session_is_transaction_0_inside_it_counts_on():
    info = (struct.pack("<HIH", 100, 0, 0) + ucs2("") + struct.pack("<H", 0)
            + b"".join(struct.pack("<I", 0) for _ in range(5)) + ucs2("Acme") + ucs2("X1")
            + ucs2("1.0") + ucs2("7"))
    s, dev = session([("w", cmd(0x1001, 0)), ("r", data(0x1001, 0, info)), ("r", resp(0x2001, 0)),
                      ("w", cmd(0x1002, 0, 1)), ("r", resp(0x2001, 0)),
                      ("w", cmd(0x1001, 1)), ("r", data(0x1001, 1, info)), ("r", resp(0x2001, 1))])
    assert s.get_device_info().model == "X1"
    s.open(1)
    assert s.get_device_info().serial_number == "7"
    assert not dev.script


def test_set_prop_value_sends_data_phase():
    s, dev = opened([("w", cmd(0x1016, 1, 0x500D)), ("w", data(0x1016, 1, struct.pack("<I", 80))),
                     ("r", resp(0x2001, 1))])
    s.set_prop_value(Prop.ExposureTime, DataType.UINT32, 80)
    assert not dev.script


def test_data_phase_spanning_several_packets():
    payload = bytes(range(256)) * 6  # 1536 bytes -> 1548-byte container: 512 + 512 + 512 + 12
    raw = data(0x1009, 1, payload)
    s, dev = opened([("w", cmd(0x1009, 1, 5))] + [("r", raw[i:i + 512]) for i in range(0, len(raw), 512)]
                    + [("r", resp(0x2001, 1))], chunk_bytes=512)
    assert s.get_object(5) == payload
    assert not dev.script


def test_whole_packet_data_phase_reads_the_zero_length_packet():
    payload = b"\xab" * (1024 - 12)
    raw = data(0x1009, 1, payload)
    s, dev = opened([("w", cmd(0x1009, 1, 5)), ("r", raw[:512]), ("r", raw[512:]), ("r", b""),
                     ("r", resp(0x2001, 1))], chunk_bytes=512)
    assert s.get_object(5) == payload
    assert not dev.script


def test_short_data_phase_is_retried_then_raises():
    payload = b"\x11" * 1500

    def attempt(tid, short):
        raw = data(0x1009, tid, payload)
        reads = [raw[:512], raw[512:700]] if short else [raw[i:i + 512] for i in range(0, len(raw), 512)]
        return [("w", cmd(0x1009, tid, 5))] + [("r", r) for r in reads] + [("r", resp(0x2001, tid))]

    s, dev = opened(attempt(1, True) + attempt(2, False), chunk_bytes=512)
    assert s.get_object(5) == payload  # the short transfer was repeated once
    assert not dev.script
    dev.script = attempt(3, True) + attempt(4, True)
    with pytest.raises(ProtocolError, match="short read"):
        s.get_object(5)
    assert not dev.script


def test_device_busy_retried_with_new_transaction_ids():
    s, dev = opened([("w", cmd(0x100E, 1, 0, 0)), ("r", resp(0x2019, 1)),
                     ("w", cmd(0x100E, 2, 0, 0)), ("r", resp(0x2019, 2)),
                     ("w", cmd(0x100E, 3, 0, 0)), ("r", resp(0x2001, 3))])
    s.initiate_capture()
    assert not dev.script


def test_device_busy_bounded():
    s, dev = opened([("w", cmd(0x100E, i, 0, 0)) if k == 0 else ("r", resp(0x2019, i))
                     for i in range(1, 40) for k in (0, 1)], busy_timeout_s=0.15)
    t0 = time.monotonic()
    with pytest.raises(DeviceBusy, match="DeviceBusy after 0.15 s"):
        s.initiate_capture()
    assert time.monotonic() - t0 < 0.4


def test_session_not_open_reopens_and_repeats():
    s, dev = opened([("w", cmd(0x100B, 1, 9, 0)), ("r", resp(0x2003, 1)),
                     ("w", cmd(0x1002, 0, 1)), ("r", resp(0x2001, 0)),
                     ("w", cmd(0x100B, 1, 9, 0)), ("r", resp(0x2001, 1))])
    s.delete_object(9)
    assert s.reopened == 1 and not dev.script


def test_error_response_raises_ptp_error_with_name():
    s, dev = opened([("w", cmd(0x1008, 1, 77)), ("r", resp(0x2009, 1))])
    with pytest.raises(PtpError, match="InvalidObjectHandle") as info:
        s.get_object_info(77)
    assert info.value.code == 0x2009 and isinstance(info.value, DeviceError)


def test_stall_clears_halt_and_repeats_idempotent_op():
    pipe = usb.core.USBError("Pipe error", -9, errno.EPIPE)
    s, dev = opened([("w", cmd(0x1015, 1, 0x500F)), ("r", pipe),
                     ("w", cmd(0x1015, 2, 0x500F)), ("r", data(0x1015, 2, b"\x90\x01")), ("r", resp(0x2001, 2))])
    assert s.get_prop_value(0x500F, DataType.UINT16) == 400
    assert dev.cleared == [IN, OUT]


def test_stall_on_capture_is_not_repeated():
    pipe = usb.core.USBError("Pipe error", -9, errno.EPIPE)
    s, dev = opened([("w", cmd(0x100E, 1, 0, 0)), ("r", pipe)])
    with pytest.raises(ProtocolError, match="stalled"):
        s.initiate_capture()
    assert dev.cleared == [IN, OUT] and not dev.script


@pytest.mark.parametrize("exc,err", [
    (usb.core.USBTimeoutError("Operation timed out", -7, errno.ETIMEDOUT), DeviceTimeout),
    (usb.core.USBError("No such device", -4, errno.ENODEV), Disconnected),
    (usb.core.USBError("Overflow", -8, errno.EOVERFLOW), ProtocolError)])
def test_usb_exceptions_become_typed_errors(exc, err):
    script = [("w", cmd(0x1015, 1, 0x500F)), ("r", exc)]
    if err is ProtocolError:  # a garbled transfer is repeated once for an idempotent operation
        script += [("w", cmd(0x1015, 2, 0x500F)), ("r", exc)]
    s, dev = opened(script)
    with pytest.raises(err):
        s.get_prop_value(0x500F, DataType.UINT16)
    assert not dev.script


def test_stale_response_from_timed_out_transaction_is_dropped():
    s, dev = opened([("w", cmd(0x1015, 1, 0x500F)), ("r", usb.core.USBTimeoutError("t", -7, errno.ETIMEDOUT)),
                     ("w", cmd(0x1015, 2, 0x500F)), ("r", data(0x1015, 1, b"\x64\x00")), ("r", resp(0x2001, 1)),
                     ("r", data(0x1015, 2, b"\x90\x01")), ("r", resp(0x2001, 2))])
    with pytest.raises(DeviceTimeout):
        s.get_prop_value(0x500F, DataType.UINT16)
    # the timed-out transaction was cancelled with the class request, then the status polled
    assert dev.control == [(0x21, 0x64, 0, struct.pack("<HI", 0x4001, 1)), (0xA1, 0x67, 0, 64)]
    assert s.get_prop_value(0x500F, DataType.UINT16) == 400


def test_events_read_from_interrupt_endpoint():
    ev = struct.pack("<IHHII", 16, 4, 0x4002, 3, 0x42)
    s, dev = session([("e", ev), ("e", usb.core.USBTimeoutError("t", -7, errno.ETIMEDOUT))])
    e = s.read_event(0.1)
    assert (e.code, e.transaction_id, e.params) == (Event.ObjectAdded, 3, (0x42,))
    assert s.read_event(0.01) is None
    s2, _ = session([("e", resp(0x2001, 1))])
    with pytest.raises(ProtocolError, match="interrupt"):
        s2.read_event(0.1)
