"""A PTP still camera as a pyusb backend: ``usb.core.find(backend=PtpCameraSim())`` finds it.

The simulator is a ``usb.backend.IBackend``: it enumerates one device with a still-image interface
(class 6/1/1: bulk OUT 0x01, bulk IN 0x82, interrupt IN 0x83) and runs camera firmware behind
the endpoints, byte for byte as ISO 15740 describes. No libusb is involved, so CI exercises the
real driver code path through pyusb.

Firmware model
--------------
- Sessions and transaction ids (OpenSession is transaction 0; ids must increase).
- Properties ExposureTime (0x500D, UINT32, 1/10000 s), ExposureIndex (0x500F, UINT16 ISO) and
  FNumber (0x5007, UINT16, x100), each with an enumerated list of allowed values.
- InitiateCapture renders a frame (``frame_source(state)`` -> DNG bytes), stores it as an object,
  and queues ObjectAdded then CaptureComplete on the interrupt endpoint once the exposure (and
  readout) time has passed (at once with ``fast=True``).
- GetObjectInfo / GetObject (a data phase split into ``max_packet`` packets, ending in a short or
  zero-length packet) / GetPartialObject (bytes ``offset`` .. ``offset + max_bytes`` of an object,
  response parameter: the bytes sent) / DeleteObject.
- What generic clients (libgphoto2, ptpy) ask after OpenSession, all advertised in DeviceInfo:
  GetStorageIDs (one removable card), GetStorageInfo (removable RAM, DCF file system, read-write,
  ``card_bytes`` capacity and what is free of it), GetNumObjects / GetObjectHandles (all stores,
  format filter, root association), GetThumb (a JPEG thumbnail of the raw mosaic, at most 160
  pixels wide, also described in ObjectInfo; NoThumbnailPresent for bytes that are not a TIFF/DNG).

Behaviours that break real tethered bracketing:

- DeviceBusy (0x2019) for ``busy_after_capture_s`` after a capture and ``busy_after_set_s``
  after a property change (SetDevicePropValue and InitiateCapture are refused meanwhile);
- StoreFull (0x200C) once ``store_capacity`` objects are on the card (objects not deleted);
- the session closes after ``session_timeout_s`` idle (SessionNotOpen 0x2003).

Faults (:meth:`PtpCameraSim.inject`): ``no_reply`` (the next command is swallowed; its bulk read
times out), ``stall`` (the next bulk read stalls the IN endpoint, EPIPE until clear_halt),
``stall_midway`` (the next data phase stalls the IN endpoint at the first bulk read after half of
it was read; the transaction is lost, as on a cable glitch during a large download),
``short_read`` (the next data phase ends early), ``corrupt_object`` (the next GetObject returns
damaged, shortened bytes), ``disconnect`` (ENODEV from then on, until :meth:`reconnect`).

The simulator must not import ``rig``: it restates the wire format here.
"""
from __future__ import annotations

import errno
import io
import struct
import time
from collections import deque
from datetime import datetime, timezone
from typing import Any, Callable

import cv2
import numpy as np
import tifffile
import usb.backend
import usb.core

from .dng import write_dng
from .faults import FaultInjection

_HDR = struct.Struct("<IHHI")
CMD, DATA, RESP, EVENT = 1, 2, 3, 4
EP_OUT, EP_IN, EP_EVENT = 0x01, 0x82, 0x83
STORAGE_ID = 0x00010001
FORMAT_DNG, FORMAT_JPEG = 0x3811, 0x3801
# StorageInfo codes (ISO 15740 5.5.4): removable RAM (a card), DCF file system, read-write
STORAGE_REMOVABLE_RAM, FILESYSTEM_DCF, ACCESS_READ_WRITE = 0x0004, 0x0003, 0x0000
THUMB_MAX_WIDTH = 160  # pixels

# operation, response, event and property codes (ISO 15740)
OP = dict(GetDeviceInfo=0x1001, OpenSession=0x1002, CloseSession=0x1003, GetStorageIDs=0x1004,
          GetStorageInfo=0x1005, GetNumObjects=0x1006, GetObjectHandles=0x1007,
          GetObjectInfo=0x1008, GetObject=0x1009, GetThumb=0x100A, DeleteObject=0x100B,
          InitiateCapture=0x100E, GetDevicePropDesc=0x1014, GetDevicePropValue=0x1015,
          SetDevicePropValue=0x1016, GetPartialObject=0x101B)
OK, GENERAL_ERROR, SESSION_NOT_OPEN, INVALID_TID = 0x2001, 0x2002, 0x2003, 0x2004
OP_NOT_SUPPORTED, INVALID_STORAGE_ID, INVALID_HANDLE, PROP_NOT_SUPPORTED = 0x2005, 0x2008, 0x2009, 0x200A
NO_THUMBNAIL, INVALID_PARENT = 0x2010, 0x201A
STORE_FULL, DEVICE_BUSY, INVALID_PROP_VALUE = 0x200C, 0x2019, 0x201C
INVALID_PARAMETER, SESSION_ALREADY_OPEN = 0x201D, 0x201E
EV_OBJECT_ADDED, EV_PROP_CHANGED, EV_CAPTURE_COMPLETE = 0x4002, 0x4006, 0x400D
PROP_FNUMBER, PROP_EXPOSURE, PROP_ISO = 0x5007, 0x500D, 0x500F
UINT16, UINT32 = 0x0004, 0x0006

_SHUTTER = ["1/4000", "1/3200", "1/2500", "1/2000", "1/1600", "1/1250", "1/1000", "1/800", "1/640",
            "1/500", "1/400", "1/320", "1/250", "1/200", "1/160", "1/125", "1/100", "1/80", "1/60",
            "1/50", "1/40", "1/30", "1/25", "1/20", "1/15", "1/13", "1/10", "1/8", "1/6", "1/5",
            "1/4", "0.3", "0.4", "0.5", "0.6", "0.8", "1", "1.3", "1.6", "2", "2.5", "3.2", "4",
            "5", "6", "8", "10", "13", "15", "20", "25", "30"]
#: allowed ExposureTime values, 1/10000 s (third stops, 1/4000 s .. 30 s)
EXPOSURE_VALUES = tuple(sorted({round(10000 * (1 / float(s[2:]) if s.startswith("1/") else float(s)))
                                for s in _SHUTTER}))
ISO_VALUES = (100, 125, 160, 200, 250, 320, 400, 500, 640, 800, 1000, 1250, 1600, 2000, 2500,
              3200, 4000, 5000, 6400)
FNUMBER_VALUES = (280, 320, 350, 400, 450, 500, 560, 630, 710, 800, 900, 1000, 1100, 1300, 1400,
                  1600, 1800, 2000, 2200)

FrameSource = Callable[[dict[str, Any]], bytes]


# -- encoding helpers (the simulator's own copy of the wire format) ---------------------------
def _container(ctype: int, code: int, tid: int, params: tuple[int, ...] = ()) -> bytes:
    return _HDR.pack(12 + 4 * len(params), ctype, code, tid) + struct.pack(f"<{len(params)}I", *params)


def _str(text: str) -> bytes:
    return b"\x00" if not text else bytes([len(text) + 1]) + (text + "\x00").encode("utf-16-le")


def _thumbnail(data: bytes) -> tuple[bytes, int, int] | None:
    """(JPEG bytes, width, height) of a thumbnail of a DNG's mosaic, None if it is not a TIFF.

    The mosaic is subsampled by an even stride (one CFA site per 2x2 tile, so no colour mixing
    artefacts) and scaled to 8 bits by its own maximum, as a preview is.
    """
    try:
        with tifffile.TiffFile(io.BytesIO(data)) as tif:
            page = tif.pages[0]
            if page.is_contiguous and len(page.shape) == 2:  # uncompressed: read in place
                raw = np.frombuffer(data, page.dtype.newbyteorder(tif.byteorder),
                                    count=int(np.prod(page.shape)), offset=page.dataoffsets[0])
                raw = raw.reshape(page.shape)
            else:
                raw = page.asarray()
    except Exception:  # noqa: BLE001 - any frame source's bytes are acceptable
        return None
    if raw.ndim != 2 or raw.size == 0:
        return None
    stride = 2 * max(1, -(-raw.shape[1] // (2 * THUMB_MAX_WIDTH)))
    small = raw[::stride, ::stride].astype(np.float32)
    small = np.clip(small * (255.0 / max(float(small.max()), 1.0)), 0, 255).astype(np.uint8)
    ok, jpeg = cv2.imencode(".jpg", small, [cv2.IMWRITE_JPEG_QUALITY, 85])
    return (jpeg.tobytes(), small.shape[1], small.shape[0]) if ok else None


def _u16s(values) -> bytes:
    values = list(values)
    return struct.pack(f"<I{len(values)}H", len(values), *values)


def placeholder_frame(state: dict[str, Any], *, size: tuple[int, int] = (600, 400),
                      seed: int = 0) -> bytes:
    """A stand-in scene: an RGGB mosaic of a smooth gradient with shot and read noise, exposed
    as ``exposure_s * iso / 100 / fnumber**2`` (relative to 1/100 s, ISO 100, f/8), as DNG bytes.

    Parameters
    ----------
    state : dict
        Camera settings (``exposure_s``, ``iso``, ``fnumber``) plus the lab's extra state.
    size : (width, height)
        Sensor size, pixels (even numbers).
    seed : int
        Seed of the noise (combined with the capture number in ``state``).
    """
    w, h = size
    rng = np.random.default_rng([seed, int(state.get("capture_number", 0))])
    gain = state["exposure_s"] / 0.01 * state["iso"] / 100.0 * (8.0 / state["fnumber"]) ** 2
    y, x = np.mgrid[0:h, 0:w].astype(np.float32)
    scene = 0.15 + 0.6 * (x / w) * (0.5 + 0.5 * y / h)            # fraction of full scale
    electrons = rng.poisson(np.clip(scene * gain, 0, 4) * 4000.0)  # full well 16000 e-
    dn = 512 + electrons * (15000 / 16000) + rng.normal(0, 3, (h, w))
    raw = np.clip(np.rint(dn), 0, 15871).astype(np.uint16)
    return write_dng(raw, black_level=512, white_level=15871, model="SimCam PTP",
                     exposure_s=state["exposure_s"], iso=state["iso"], fnumber=state["fnumber"])


def _image_size(data: bytes) -> tuple[int, int]:
    """(width, height) of a TIFF/DNG's first image, (0, 0) if it is not one."""
    try:
        with tifffile.TiffFile(io.BytesIO(data)) as tif:
            h, w = tif.pages[0].shape[:2]
        return w, h
    except Exception:  # noqa: BLE001 - any frame source's bytes are acceptable
        return 0, 0


class _Desc:
    """A USB descriptor: fields as attributes (pyusb reads them by name)."""

    def __init__(self, **fields: Any) -> None:
        self.__dict__.update(fields)
        self.extra_descriptors = []


class _Transfer:
    """One IN transfer (a container) made of zero-copy parts; bulk reads copy out of it."""

    def __init__(self, *parts: bytes | memoryview) -> None:
        self.parts = [memoryview(p).cast("B") for p in parts if len(p)]
        self.size = sum(len(p) for p in self.parts)
        self.pos = 0
        self.sent = 0  # bytes read out so far

    def read_into(self, out: memoryview) -> int:
        n = 0
        while n < len(out) and self.parts:
            part = self.parts[0]
            take = min(len(out) - n, len(part) - self.pos)
            out[n:n + take] = part[self.pos:self.pos + take]
            n += take
            self.pos += take
            if self.pos == len(part):
                self.parts.pop(0)
                self.pos = 0
        self.sent += n
        return n

    @property
    def done(self) -> bool:
        return not self.parts


class PtpCameraSim(FaultInjection, usb.backend.IBackend):
    """Camera firmware behind a pyusb backend.

    Parameters
    ----------
    frame_source : callable, optional
        ``frame_source(state) -> bytes`` (a DNG file); ``state`` holds ``exposure_s`` (seconds),
        ``iso``, ``fnumber``, ``capture_number`` merged with ``extra_state()``. Default:
        :func:`placeholder_frame`.
    extra_state : callable, optional
        Returns a dict merged into ``state`` at each capture (turntable angle, light position,
        polarizer angle ...).
    vendor_id, product_id : int
        USB ids the device enumerates with.
    fast : bool
        Deliver capture events at once instead of after exposure + readout time.
    readout_s : float
        Sensor readout and processing time added to the exposure when not ``fast``, seconds.
    busy_after_capture_s, busy_after_set_s : float
        DeviceBusy windows after a capture and after a property change, seconds.
    session_timeout_s : float or None
        Idle time after which the camera closes the session, seconds (None: never).
    store_capacity : int
        Objects the card holds before StoreFull.
    card_bytes : int
        Capacity of the card reported in StorageInfo, bytes.
    max_packet : int
        wMaxPacketSize of the bulk endpoints, bytes.
    """

    FAULTS = frozenset({"no_reply", "stall", "stall_midway", "short_read", "corrupt_object",
                        "disconnect"})

    def __init__(self, frame_source: FrameSource | None = None, *,
                 extra_state: Callable[[], dict[str, Any]] | None = None,
                 vendor_id: int = 0x1209, product_id: int = 0x6770, fast: bool = True,
                 readout_s: float = 0.05, busy_after_capture_s: float = 0.0,
                 busy_after_set_s: float = 0.0, session_timeout_s: float | None = None,
                 store_capacity: int = 500, max_packet: int = 512,
                 serial_number: str = "SIM0001", card_bytes: int = 32 << 30) -> None:
        super().__init__()
        self.frame_source = frame_source or placeholder_frame
        self.extra_state = extra_state
        self.vendor_id, self.product_id = vendor_id, product_id
        self.fast = fast
        self.readout_s = readout_s
        self.busy_after_capture_s = busy_after_capture_s
        self.busy_after_set_s = busy_after_set_s
        self.session_timeout_s = session_timeout_s
        self.store_capacity = store_capacity
        self.card_bytes = card_bytes
        self.max_packet = max_packet
        self.serial_number = serial_number
        self._init_faults()
        self.commands: list[tuple[int, tuple[int, ...]]] = []  # (op, params) received, for tests
        self.captures = 0
        self.busy_replies = 0  # DeviceBusy answers given, for tests
        self.cancels = 0  # class Cancel requests received
        self.disconnected = False
        self._dev = object()  # the enumerated device's identity
        self.props = {PROP_EXPOSURE: [UINT32, 100, 100, EXPOSURE_VALUES],     # 1/100 s
                      PROP_ISO: [UINT16, 100, 100, ISO_VALUES],
                      PROP_FNUMBER: [UINT16, 800, 800, FNUMBER_VALUES]}      # f/8
        self._power_up()

    # -- state --------------------------------------------------------------------------------
    def _power_up(self) -> None:
        self.session_id = 0
        self._last_tid = 0
        self._last_activity = time.monotonic()
        self.objects: dict[int, dict[str, Any]] = {}
        self._next_handle = 1
        self._busy_until = 0.0
        self._in: deque[_Transfer] = deque()
        self._events: deque[tuple[float, bytes]] = deque()
        self._halted: set[int] = set()
        self._pending_data_op: tuple[int, int, tuple[int, ...]] | None = None
        for p in self.props.values():
            p[2] = p[1]

    def prop(self, code: int) -> int:
        """Current raw value of a property."""
        return self.props[code][2]

    @property
    def exposure_s(self) -> float:
        """Current exposure time, seconds."""
        return self.prop(PROP_EXPOSURE) / 10000.0

    def turn_dial(self, code: int, value: int) -> None:
        """Change a property on the camera body (its dial), as a user would: the camera announces
        it with a DevicePropChanged event."""
        with self._lock:
            if value not in self.props[code][3]:
                raise ValueError(f"0x{code:04X} does not offer {value}; allowed: {self.props[code][3]}")
            self.props[code][2] = value
            self._events.append((time.monotonic(), _container(EVENT, EV_PROP_CHANGED, 0, (code,))))

    def inject(self, fault: str, count: int = 1) -> None:
        """Arm ``fault`` (see the module docstring) for its next ``count`` occurrences;
        ``disconnect`` pulls the cable at once."""
        super().inject(fault, count)
        if fault == "disconnect":
            self.take_fault("disconnect")
            self.disconnect()

    def disconnect(self) -> None:
        """Pull the cable: every transfer fails with ENODEV and the device no longer enumerates."""
        with self._lock:
            self.disconnected = True

    def reconnect(self) -> None:
        """Plug back in: the camera enumerates again with power-up state (no session, card kept)."""
        with self._lock:
            objects, handle = self.objects, self._next_handle
            self._power_up()
            self.objects, self._next_handle = objects, handle
            self.disconnected = False

    # -- USB errors ---------------------------------------------------------------------------
    def _check(self, ep: int | None = None) -> None:
        if self.disconnected:
            raise usb.core.USBError("No such device (it may have been disconnected)", -4,
                                    errno.ENODEV)
        if ep is not None and ep in self._halted:
            raise usb.core.USBError("Pipe error", -9, errno.EPIPE)

    @staticmethod
    def _timeout(timeout_ms: int) -> None:
        time.sleep(max(timeout_ms, 1) / 1000.0)
        raise usb.core.USBTimeoutError("Operation timed out", -7, errno.ETIMEDOUT)

    # -- descriptors and enumeration ----------------------------------------------------------
    def enumerate_devices(self):
        if not self.disconnected:
            yield self._dev

    def get_device_descriptor(self, dev):
        return _Desc(bLength=18, bDescriptorType=1, bcdUSB=0x0200, bDeviceClass=0,
                     bDeviceSubClass=0, bDeviceProtocol=0, bMaxPacketSize0=64,
                     idVendor=self.vendor_id, idProduct=self.product_id, bcdDevice=0x0100,
                     iManufacturer=1, iProduct=2, iSerialNumber=3, bNumConfigurations=1,
                     address=5, bus=1, port_number=2, port_numbers=(2,), speed=3)

    def get_configuration_descriptor(self, dev, config):
        if config != 0:
            raise IndexError(config)
        return _Desc(bLength=9, bDescriptorType=2, wTotalLength=39, bNumInterfaces=1,
                     bConfigurationValue=1, iConfiguration=0, bmAttributes=0xC0, bMaxPower=1)

    def get_interface_descriptor(self, dev, intf, alt, config):
        if intf != 0 or alt != 0 or config != 0:
            raise IndexError((intf, alt, config))
        return _Desc(bLength=9, bDescriptorType=4, bInterfaceNumber=0, bAlternateSetting=0,
                     bNumEndpoints=3, bInterfaceClass=6, bInterfaceSubClass=1,
                     bInterfaceProtocol=1, iInterface=0)

    def get_endpoint_descriptor(self, dev, ep, intf, alt, config):
        table = [(EP_OUT, 2, self.max_packet, 0), (EP_IN, 2, self.max_packet, 0),
                 (EP_EVENT, 3, 64, 8)]
        if intf != 0 or alt != 0 or config != 0 or not 0 <= ep < len(table):
            raise IndexError(ep)
        addr, attrs, size, interval = table[ep]
        return _Desc(bLength=7, bDescriptorType=5, bEndpointAddress=addr, bmAttributes=attrs,
                     wMaxPacketSize=size, bInterval=interval, bRefresh=0, bSynchAddress=0)

    def get_parent(self, dev):
        return None

    def open_device(self, dev):
        self._check()
        return self

    def close_device(self, dev_handle) -> None:
        pass

    def set_configuration(self, dev_handle, config_value) -> None:
        self._check()

    def get_configuration(self, dev_handle) -> int:
        self._check()
        return 1

    def set_interface_altsetting(self, dev_handle, intf, altsetting) -> None:
        self._check()

    def claim_interface(self, dev_handle, intf) -> None:
        self._check()

    def release_interface(self, dev_handle, intf) -> None:
        pass

    def is_kernel_driver_active(self, dev_handle, intf) -> bool:
        return False

    def clear_halt(self, dev_handle, ep) -> None:
        with self._lock:
            self._check()
            self._halted.discard(ep)

    def reset_device(self, dev_handle) -> None:
        with self._lock:
            self._check()
            self.reconnect()

    def ctrl_transfer(self, dev_handle, bmRequestType, bRequest, wValue, wIndex, data, timeout):
        """Still-image class requests: Cancel (0x64), Device Reset (0x66), Get Device Status
        (0x67)."""
        with self._lock:
            self._check()
            if bmRequestType == 0x21 and bRequest == 0x64:
                self.cancels += 1
                self._in.clear()  # the cancelled transaction's data and response are dropped
                self._pending_data_op = None
                return len(data)
            if bmRequestType == 0xA1 and bRequest == 0x67:
                code = DEVICE_BUSY if time.monotonic() < self._busy_until else OK
                status = struct.pack("<HH", 4, code)
                n = min(len(data), 4)
                data[:n] = type(data)("B", status[:n])
                return n
            if bmRequestType == 0x21 and bRequest == 0x66:
                self._in.clear()
                self.session_id = 0
                return 0
            raise usb.core.USBError("Pipe error", -9, errno.EPIPE)

    # -- transfers ----------------------------------------------------------------------------
    def bulk_write(self, dev_handle, ep, intf, data, timeout) -> int:
        with self._lock:
            self._check(ep)
            raw = bytes(data)
            if not raw:  # zero-length packet ending a whole-packet transfer
                return 0
            if len(raw) < 12:
                self._halted.add(EP_OUT)
                raise usb.core.USBError("Pipe error", -9, errno.EPIPE)
            length, ctype, code, tid = _HDR.unpack_from(raw)
            if ctype == DATA and self._pending_data_op is not None:
                op, ptid, params = self._pending_data_op
                self._pending_data_op = None
                self._reply(op, ptid, *self._set_prop(params, raw[12:length]))
            elif ctype == CMD:
                params = struct.unpack(f"<{(length - 12) // 4}I", raw[12:length])
                self.commands.append((code, params))
                if self.take_fault("no_reply"):
                    return len(raw)
                self._command(code, tid, params)
            return len(raw)

    def bulk_read(self, dev_handle, ep, intf, buff, timeout) -> int:
        with self._lock:
            self._check(ep)
            if self._in and self.take_fault("stall"):
                self._in.clear()  # the in-flight transfer is lost
                self._halted.add(ep)
                raise usb.core.USBError("Pipe error", -9, errno.EPIPE)
            if self._in:
                xfer = self._in[0]
                if xfer.size > 2 * self.max_packet and xfer.sent >= xfer.size // 2 \
                        and self.take_fault("stall_midway"):
                    self._in.clear()  # the rest of the data phase and its response are lost
                    self._halted.add(ep)
                    raise usb.core.USBError("Pipe error", -9, errno.EPIPE)
                n = xfer.read_into(memoryview(buff).cast("B"))
                if xfer.done:
                    self._in.popleft()
                return n
        self._timeout(timeout)

    def intr_read(self, dev_handle, ep, intf, buff, timeout) -> int:
        deadline = time.monotonic() + max(timeout, 1) / 1000.0
        while True:
            with self._lock:
                self._check(ep)
                if self._events and self._events[0][0] <= time.monotonic():
                    event = self._events.popleft()[1]
                    n = min(len(buff), len(event))
                    memoryview(buff).cast("B")[:n] = event[:n]
                    return n
            if time.monotonic() >= deadline:
                raise usb.core.USBTimeoutError("Operation timed out", -7, errno.ETIMEDOUT)
            time.sleep(0.001)

    # -- firmware -----------------------------------------------------------------------------
    def _reply(self, op: int, tid: int, code: int, params: tuple[int, ...] = (),
               data: bytes | memoryview | None = None) -> None:
        self.busy_replies += code == DEVICE_BUSY
        if data is not None:
            self._queue_data(op, tid, data)
        self._in.append(_Transfer(_container(RESP, code, tid, params)))

    def _queue_data(self, op: int, tid: int, data: bytes | memoryview) -> None:
        header = _HDR.pack(12 + len(data), DATA, op, tid)
        if self.take_fault("short_read"):
            cut = max(1, (len(data) // 2) // self.max_packet * self.max_packet - 100)
            self._in.append(_Transfer(header, memoryview(data)[:cut]))  # a short packet, too soon
            return
        self._in.append(_Transfer(header, data))
        if (12 + len(data)) % self.max_packet == 0:
            self._in.append(_Transfer())  # zero-length packet

    def _command(self, op: int, tid: int, params: tuple[int, ...]) -> None:
        now = time.monotonic()
        if (self.session_id and self.session_timeout_s is not None
                and now - self._last_activity > self.session_timeout_s):
            self.session_id = 0  # idle too long: the camera dropped the session
        self._last_activity = now
        if op == OP["GetDeviceInfo"] and not self.session_id:
            if tid != 0:  # outside a session the TransactionID must be 0
                return self._reply(op, tid, INVALID_TID)
            return self._reply(op, tid, OK, data=self._device_info())
        if op == OP["OpenSession"]:
            if not params or params[0] == 0:
                return self._reply(op, tid, INVALID_PARAMETER)
            if self.session_id:
                return self._reply(op, tid, SESSION_ALREADY_OPEN, (self.session_id,))
            self.session_id, self._last_tid = params[0], 0
            return self._reply(op, tid, OK)
        if not self.session_id:
            return self._reply(op, tid, SESSION_NOT_OPEN)
        if tid <= self._last_tid:
            return self._reply(op, tid, INVALID_TID)
        self._last_tid = tid
        if op == OP["CloseSession"]:
            self.session_id = 0
            return self._reply(op, tid, OK)
        if op == OP["GetDeviceInfo"]:
            return self._reply(op, tid, OK, data=self._device_info())
        if op == OP["GetStorageIDs"]:
            return self._reply(op, tid, OK, data=struct.pack("<II", 1, STORAGE_ID))
        if op == OP["GetStorageInfo"]:
            if not params or params[0] != STORAGE_ID:
                return self._reply(op, tid, INVALID_STORAGE_ID)
            return self._reply(op, tid, OK, data=self._storage_info())
        if op in (OP["GetNumObjects"], OP["GetObjectHandles"]):
            handles = self._select(params)
            if isinstance(handles, int):
                return self._reply(op, tid, handles)
            if op == OP["GetNumObjects"]:
                return self._reply(op, tid, OK, (len(handles),))
            return self._reply(op, tid, OK, data=struct.pack(f"<I{len(handles)}I", len(handles), *handles))
        if op in (OP["GetDevicePropDesc"], OP["GetDevicePropValue"]):
            code = params[0] if params else 0
            if code not in self.props:
                return self._reply(op, tid, PROP_NOT_SUPPORTED)
            return self._reply(op, tid, OK, data=self._prop_desc(code) if op == OP["GetDevicePropDesc"]
                               else self._prop_value(code))
        if op == OP["SetDevicePropValue"]:
            self._pending_data_op = (op, tid, params)  # the data phase carries the value
            return None
        if op == OP["InitiateCapture"]:
            return self._reply(op, tid, *self._capture(tid))
        if op in (OP["GetObjectInfo"], OP["GetObject"], OP["DeleteObject"], OP["GetThumb"],
                  OP["GetPartialObject"]):
            return self._object_op(op, tid, params)
        return self._reply(op, tid, OP_NOT_SUPPORTED)

    def _device_info(self) -> bytes:
        return (struct.pack("<HIH", 100, 0, 0) + _str("") + struct.pack("<H", 0)
                + _u16s(sorted(OP.values()))
                + _u16s([EV_OBJECT_ADDED, EV_PROP_CHANGED, EV_CAPTURE_COMPLETE])
                + _u16s(sorted(self.props)) + _u16s([FORMAT_DNG]) + _u16s([FORMAT_DNG])
                + _str("gonio") + _str("SimCam PTP") + _str("1.0.0") + _str(self.serial_number))

    def _prop_desc(self, code: int) -> bytes:
        dtype, default, current, values = self.props[code]
        f = "<I" if dtype == UINT32 else "<H"
        enum = struct.pack("<H", len(values)) + b"".join(struct.pack(f, v) for v in values)
        return (struct.pack("<HHB", code, dtype, 1) + struct.pack(f, default)
                + struct.pack(f, current) + b"\x02" + enum)

    def _prop_value(self, code: int) -> bytes:
        dtype, _, current, _ = self.props[code]
        return struct.pack("<I" if dtype == UINT32 else "<H", current)

    def _set_prop(self, params: tuple[int, ...], payload: bytes) -> tuple[int]:
        code = params[0] if params else 0
        if code not in self.props:
            return (PROP_NOT_SUPPORTED,)
        now = time.monotonic()
        if now < self._busy_until:
            return (DEVICE_BUSY,)
        dtype, _, _, values = self.props[code]
        size = 4 if dtype == UINT32 else 2
        if len(payload) != size:
            return (0x201B,)  # InvalidDevicePropFormat
        value = int.from_bytes(payload, "little")
        if value not in values:
            return (INVALID_PROP_VALUE,)
        self.props[code][2] = value
        self._busy_until = now + self.busy_after_set_s
        self._events.append((now, _container(EVENT, EV_PROP_CHANGED, 0, (code,))))
        return (OK,)

    def _capture(self, tid: int) -> tuple[int]:
        now = time.monotonic()
        if now < self._busy_until:
            return (DEVICE_BUSY,)
        if len(self.objects) >= self.store_capacity:
            return (STORE_FULL,)
        self.captures += 1
        state = {"exposure_s": self.exposure_s, "iso": self.prop(PROP_ISO),
                 "fnumber": self.prop(PROP_FNUMBER) / 100.0, "capture_number": self.captures}
        if self.extra_state is not None:
            state.update(self.extra_state())
        data = self.frame_source(state)
        handle = self._next_handle
        self._next_handle += 1
        stamp = datetime.now(timezone.utc).strftime("%Y%m%dT%H%M%S.0")
        ready = now if self.fast else now + state["exposure_s"] + self.readout_s
        self.objects[handle] = {"data": data, "filename": f"IMG_{handle:04d}.DNG", "date": stamp,
                                "ready": ready, "state": state, "size": _image_size(data)}
        self._events.append((ready, _container(EVENT, EV_OBJECT_ADDED, tid, (handle,))))
        self._events.append((ready, _container(EVENT, EV_CAPTURE_COMPLETE, tid)))
        self._busy_until = ready + self.busy_after_capture_s
        return (OK,)

    def _storage_info(self) -> bytes:
        """StorageInfo dataset (ISO 15740 5.5.4)."""
        used = sum(len(o["data"]) for o in self.objects.values())
        return (struct.pack("<HHHQQI", STORAGE_REMOVABLE_RAM, FILESYSTEM_DCF, ACCESS_READ_WRITE,
                            self.card_bytes, max(0, self.card_bytes - used),
                            max(0, self.store_capacity - len(self.objects)))
                + _str("SD card") + _str("GONIO"))

    def _select(self, params: tuple[int, ...]) -> list[int] | int:
        """Handles for GetNumObjects / GetObjectHandles (StorageID, ObjectFormatCode,
        association), or the response code refusing the parameters."""
        storage, fmt, parent = (tuple(params) + (0, 0, 0))[:3]
        if storage not in (0xFFFFFFFF, STORAGE_ID):
            return INVALID_STORAGE_ID
        if parent not in (0, 0xFFFFFFFF):  # objects sit in the root: no association holds any
            return INVALID_PARENT
        now = time.monotonic()
        return sorted(h for h, o in self.objects.items()
                      if o["ready"] <= now and fmt in (0, 0xFFFFFFFF, FORMAT_DNG))  # all / images / DNG

    def _thumb(self, obj: dict[str, Any]) -> tuple[bytes, int, int] | None:
        if "thumb" not in obj:
            obj["thumb"] = _thumbnail(obj["data"])
        return obj["thumb"]

    def _object_info(self, obj: dict[str, Any]) -> bytes:
        w, h = obj["size"]
        thumb = self._thumb(obj)
        thumb_fields = (FORMAT_JPEG, len(thumb[0]), thumb[1], thumb[2]) if thumb else (0, 0, 0, 0)
        return (struct.pack("<IHHIHIIIIIIIHII", STORAGE_ID, FORMAT_DNG, 0, len(obj["data"]),
                            *thumb_fields, w, h, 16, 0, 0, 0, 0)
                + _str(obj["filename"]) + _str(obj["date"]) + _str(obj["date"]) + _str(""))

    def _object_op(self, op: int, tid: int, params: tuple[int, ...]) -> None:
        handle = params[0] if params else 0
        if op == OP["DeleteObject"] and handle == 0xFFFFFFFF:
            self.objects.clear()
            return self._reply(op, tid, OK)
        obj = self.objects.get(handle)
        if obj is None or obj["ready"] > time.monotonic():
            return self._reply(op, tid, INVALID_HANDLE)
        if op == OP["GetObjectInfo"]:
            return self._reply(op, tid, OK, data=self._object_info(obj))
        if op == OP["DeleteObject"]:
            del self.objects[handle]
            return self._reply(op, tid, OK)
        if op == OP["GetThumb"]:
            thumb = self._thumb(obj)
            return self._reply(op, tid, OK, data=thumb[0]) if thumb else self._reply(op, tid, NO_THUMBNAIL)
        if op == OP["GetPartialObject"]:
            offset, max_bytes = (tuple(params[1:]) + (0, 0))[:2]
            if offset > len(obj["data"]):
                return self._reply(op, tid, INVALID_PARAMETER)
            part = memoryview(obj["data"])[offset:offset + max_bytes]
            return self._reply(op, tid, OK, (len(part),), data=part)
        data = obj["data"]
        if self.take_fault("corrupt_object"):
            damaged = bytearray(data[: max(0, len(data) - 4096)])
            damaged[len(damaged) // 2: len(damaged) // 2 + 64] = bytes(64)
            data = bytes(damaged)
        return self._reply(op, tid, OK, data=memoryview(data))
