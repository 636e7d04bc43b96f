"""The simulated PTP camera seen through plain pyusb (no gonio driver): descriptors, firmware."""
from __future__ import annotations

import array
import errno
import struct
import time

import pytest
import usb.core
import usb.util

from sims.ptp_sim import EXPOSURE_VALUES, PtpCameraSim, placeholder_frame


def cmd(op, tid, *params):
    return struct.pack(f"<IHHI{len(params)}I", 12 + 4 * len(params), 1, op, tid, *params)


class Raw:
    """Bare transactions through pyusb against the simulator."""

    def __init__(self, sim):
        self.dev = usb.core.find(idVendor=0x1209, idProduct=0x6770, backend=sim)
        self.dev.set_configuration()

    def read(self, size=1 << 20, ep=0x82, timeout=200):
        buf = array.array("B", bytes(size))
        n = self.dev.read(ep, buf, timeout)
        return bytes(buf[:n])

    def run(self, op, tid, *params, data=None):
        self.dev.write(0x01, cmd(op, tid, *params), 200)
        if data is not None:
            self.dev.write(0x01, struct.pack("<IHHI", 12 + len(data), 2, op, tid) + data, 200)
        payload = None
        while True:
            c = self.read()
            length, ctype, code, t = struct.unpack_from("<IHHI", c)
            assert t == tid and length == len(c)
            if ctype == 2:
                payload = c[12:]
                continue
            return code, struct.unpack(f"<{(length - 12) // 4}I", c[12:]), payload


def test_enumerates_as_still_image_device():
    sim = PtpCameraSim()
    dev = usb.core.find(idVendor=0x1209, idProduct=0x6770, backend=sim)
    assert dev is not None
    assert usb.core.find(idVendor=0x1209, idProduct=0x0001, backend=sim) is None
    dev.set_configuration()
    intf = usb.util.find_descriptor(dev.get_active_configuration(), bInterfaceClass=6)
    assert (intf.bInterfaceSubClass, intf.bInterfaceProtocol) == (1, 1)
    eps = [(e.bEndpointAddress, usb.util.endpoint_type(e.bmAttributes)) for e in intf]
    assert eps == [(0x01, usb.util.ENDPOINT_TYPE_BULK), (0x82, usb.util.ENDPOINT_TYPE_BULK),
                   (0x83, usb.util.ENDPOINT_TYPE_INTR)]


def test_session_rules_and_transaction_ids():
    r = Raw(PtpCameraSim())
    assert r.run(0x1001, 3)[0] == 0x2004                  # outside a session the id must be 0
    code, _, info = r.run(0x1001, 0)                      # GetDeviceInfo needs no session
    assert code == 0x2001 and struct.unpack_from("<H", info)[0] == 100  # PTP 1.00
    assert r.run(0x1015, 1, 0x500D)[0] == 0x2003          # SessionNotOpen
    assert r.run(0x1002, 0, 0)[0] == 0x201D               # session id 0 is invalid
    assert r.run(0x1002, 0, 7)[0] == 0x2001
    assert r.run(0x1002, 0, 7)[:2] == (0x201E, (7,))      # SessionAlreadyOpen
    assert r.run(0x1015, 1, 0x500D)[0] == 0x2001
    assert r.run(0x1015, 1, 0x500D)[0] == 0x2004          # transaction id reused
    assert r.run(0x1001, 2)[0] == 0x2001                  # in a session: the next id
    assert r.run(0x9999, 3)[0] == 0x2005                  # OperationNotSupported
    assert r.run(0x1015, 4, 0x5001)[0] == 0x200A          # DevicePropNotSupported
    assert r.run(0x1003, 5)[0] == 0x2001
    assert r.run(0x1015, 6, 0x500D)[0] == 0x2003


def test_property_values_enumerated_and_enforced():
    sim = PtpCameraSim()
    r = Raw(sim)
    r.run(0x1002, 0, 1)
    code, _, desc = r.run(0x1014, 1, 0x500D)
    assert code == 0x2001 and struct.unpack_from("<HHB", desc) == (0x500D, 6, 1)
    n = struct.unpack_from("<H", desc, 14)[0]
    assert struct.unpack_from(f"<{n}I", desc, 16) == EXPOSURE_VALUES
    assert r.run(0x1016, 2, 0x500D, data=struct.pack("<I", 123))[0] == 0x201C  # not enumerated
    assert r.run(0x1016, 3, 0x500D, data=struct.pack("<H", 10))[0] == 0x201B   # wrong size
    assert r.run(0x1016, 4, 0x500D, data=struct.pack("<I", 40))[0] == 0x2001
    assert sim.exposure_s == 0.004


def test_capture_events_object_and_zero_length_packet():
    def source(state):  # a data phase that is an exact multiple of 512 bytes
        return b"\x5a" * (4 * 512 - 12)

    sim = PtpCameraSim(source)
    r = Raw(sim)
    r.run(0x1002, 0, 1)
    assert r.run(0x100E, 1, 0, 0)[0] == 0x2001
    ev1, ev2 = r.read(64, ep=0x83), r.read(64, ep=0x83)
    assert struct.unpack("<IHHII", ev1) == (16, 4, 0x4002, 1, 1)   # ObjectAdded, handle 1
    assert struct.unpack("<IHHI", ev2) == (12, 4, 0x400D, 1)       # CaptureComplete
    r.dev.write(0x01, cmd(0x1009, 2, 1), 200)
    sizes = [len(r.read(512)) for _ in range(4)]
    assert sizes == [512] * 4
    assert r.read(512) == b""                                       # ZLP ends the data phase
    assert struct.unpack("<IHHI", r.read(512)) == (12, 3, 0x2001, 2)
    assert r.run(0x100B, 3, 1, 0)[0] == 0x2001 and sim.objects == {}
    assert r.run(0x1008, 4, 1)[0] == 0x2009                         # deleted: invalid handle


def test_timed_capture_and_busy_window():
    sim = PtpCameraSim(lambda s: b"z" * 100, fast=False, readout_s=0.05, busy_after_capture_s=0.1)
    r = Raw(sim)
    r.run(0x1002, 0, 1)
    r.run(0x1016, 1, 0x500D, data=struct.pack("<I", 1000))          # 0.1 s
    assert struct.unpack("<IHHII", r.read(64, ep=0x83)) == (16, 4, 0x4006, 0, 0x500D)  # PropChanged
    t0 = time.monotonic()
    r.run(0x100E, 2, 0, 0)
    with pytest.raises(usb.core.USBTimeoutError):
        r.read(64, ep=0x83, timeout=50)                              # not exposed yet
    assert r.run(0x1008, 3, 1)[0] == 0x2009                         # object not ready
    r.read(64, ep=0x83, timeout=500)
    assert time.monotonic() - t0 >= 0.15
    assert r.run(0x100E, 4, 0, 0)[0] == 0x2019                      # DeviceBusy
    time.sleep(0.12)
    assert r.run(0x100E, 5, 0, 0)[0] == 0x2001


def test_store_fills_and_session_times_out():
    sim = PtpCameraSim(lambda s: b"x" * 100, store_capacity=2, session_timeout_s=0.1)
    r = Raw(sim)
    r.run(0x1002, 0, 1)
    assert [r.run(0x100E, t, 0, 0)[0] for t in (1, 2, 3)] == [0x2001, 0x2001, 0x200C]
    assert struct.unpack("<3I", r.run(0x1007, 4, 0xFFFFFFFF, 0, 0)[2]) == (2, 1, 2)
    time.sleep(0.15)
    assert r.run(0x1008, 5, 1)[0] == 0x2003


def test_faults():
    sim = PtpCameraSim(lambda s: b"y" * 5000)
    r = Raw(sim)
    r.run(0x1002, 0, 1)
    sim.inject("no_reply")
    r.dev.write(0x01, cmd(0x1015, 1, 0x500D), 200)
    t0 = time.monotonic()
    with pytest.raises(usb.core.USBTimeoutError):
        r.read(timeout=100)
    assert 0.09 < time.monotonic() - t0 < 0.5
    sim.inject("stall")
    r.dev.write(0x01, cmd(0x1015, 2, 0x500D), 200)
    for _ in range(2):  # halted until cleared
        with pytest.raises(usb.core.USBError) as info:
            r.read()
        assert info.value.errno == errno.EPIPE
    r.dev.clear_halt(0x82)
    assert r.run(0x1015, 3, 0x500D)[0] == 0x2001
    r.run(0x100E, 4, 0, 0)
    sim.inject("short_read")
    r.dev.write(0x01, cmd(0x1009, 5, 1), 200)
    first = r.read(1 << 16)
    assert struct.unpack_from("<I", first)[0] == 5012 and len(first) < 5012
    assert struct.unpack("<IHHI", r.read())[2] == 0x2001
    sim.inject("corrupt_object")
    code, _, payload = r.run(0x1009, 6, 1)
    assert code == 0x2001 and len(payload) < 5000
    sim.inject("disconnect")
    with pytest.raises(usb.core.USBError) as info:
        r.run(0x1015, 7, 0x500D)
    assert info.value.errno == errno.ENODEV
    assert usb.core.find(idVendor=0x1209, idProduct=0x6770, backend=sim) is None
    with pytest.raises(ValueError, match="unknown fault"):
        sim.inject("smoke")


def test_placeholder_frame_scales_with_exposure():
    import io
    import rawpy
    means = []
    for t in (0.001, 0.002):
        with rawpy.imread(io.BytesIO(placeholder_frame({"exposure_s": t, "iso": 100, "fnumber": 8.0},
                                                       size=(64, 48)))) as raw:
            means.append(raw.raw_image.astype(float).mean() - 512)
    assert means[1] / means[0] == pytest.approx(2.0, rel=0.05)


def test_storage_object_enumeration_thumb_and_partial_refusals():
    """What generic clients ask after OpenSession, and the ISO 15740 refusals of bad parameters."""
    blob = b"not a TIFF, so no thumbnail" * 40
    sim = PtpCameraSim(frame_source=lambda state: blob)
    r = Raw(sim)
    assert r.run(0x1002, 0, 1)[0] == 0x2001
    assert r.run(0x100E, 1)[0] == 0x2001
    code, _, info = r.run(0x1005, 2, 0x00010001)                      # GetStorageInfo
    assert code == 0x2001
    assert struct.unpack_from("<HHHQQI", info) == (4, 3, 0, sim.card_bytes,
                                                   sim.card_bytes - len(blob), sim.store_capacity - 1)
    assert r.run(0x1005, 3, 0x00020001)[0] == 0x2008                  # InvalidStorageID
    assert r.run(0x1006, 4, 0xFFFFFFFF, 0, 0) == (0x2001, (1,), None)  # GetNumObjects
    assert r.run(0x1006, 5, 0xFFFFFFFF, 0x3801, 0)[1] == (0,)         # no JPEG on the card
    assert r.run(0x1007, 6, 0xFFFFFFFF, 0, 7)[0] == 0x201A            # not an association
    assert r.run(0x100A, 7, 1)[0] == 0x2010                           # NoThumbnailPresent
    code, _, objinfo = r.run(0x1008, 8, 1)
    assert struct.unpack_from("<HIII", objinfo, 12) == (0, 0, 0, 0)   # ObjectInfo: no thumb either
    assert r.run(0x101B, 9, 1, len(blob) + 1, 10)[0] == 0x201D        # offset past the end
    assert r.run(0x101B, 10, 1, len(blob) - 10, 100) == (0x2001, (10,), blob[-10:])
    assert r.run(0x101B, 11, 2, 0, 10)[0] == 0x2009                   # InvalidObjectHandle
