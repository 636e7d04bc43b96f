"""PTP (ISO 15740, Picture Transfer Protocol) over USB: container codec, datasets, session.

USB still-image class (interface class 6, subclass 1, protocol 1): one bulk OUT endpoint carries
command (and host->device data) containers, one bulk IN endpoint data and response containers,
one interrupt IN endpoint event containers. Every container is little-endian::

    uint32 length | uint16 type | uint16 code | uint32 transaction id | payload
    type: 1 command, 2 data, 3 response, 4 event; command/response/event payload: 0..5 uint32 params

A transaction is command -> [data phase, either direction] -> response. A data phase longer than
one transfer arrives in several bulk reads; it ends with a short packet, or a zero-length packet
when its length is a multiple of ``wMaxPacketSize``. Strings are a count byte (characters
including the NUL) followed by UCS-2 little-endian characters; arrays are a uint32 count then the
elements.

:class:`PtpSession` runs transactions over a pyusb device: transaction ids, DeviceBusy (0x2019)
retry with bounded exponential back-off, stall recovery (clear halt, retry idempotent operations),
short data phases, stale replies after a timeout, re-opening a session the device closed
(SessionNotOpen 0x2003), and resuming a download broken off part way with GetPartialObject
(0x101B) from the first byte missing. pyusb exceptions never leave this module: timeouts become
``DeviceTimeout``, a vanished device ``Disconnected``, anything else ``ProtocolError``.
"""
from __future__ import annotations

import array
import errno
import logging
import struct
import threading
import time
from dataclasses import dataclass
from enum import IntEnum
from typing import Any

import usb.core

from .errors import DeviceBusy, DeviceError, DeviceTimeout, Disconnected, ProtocolError

log = logging.getLogger("gonio.rig.ptp")

HEADER = struct.Struct("<IHHI")
HEADER_SIZE = HEADER.size  # 12 bytes
MAX_PARAMS = 5


class ContainerType(IntEnum):
    COMMAND = 1
    DATA = 2
    RESPONSE = 3
    EVENT = 4


class Op(IntEnum):
    """Operation codes (ISO 15740 table 18)."""

    GetDeviceInfo = 0x1001
    OpenSession = 0x1002
    CloseSession = 0x1003
    GetStorageIDs = 0x1004
    GetStorageInfo = 0x1005
    GetNumObjects = 0x1006
    GetObjectHandles = 0x1007
    GetObjectInfo = 0x1008
    GetObject = 0x1009
    GetThumb = 0x100A
    DeleteObject = 0x100B
    InitiateCapture = 0x100E
    GetDevicePropDesc = 0x1014
    GetDevicePropValue = 0x1015
    SetDevicePropValue = 0x1016
    GetPartialObject = 0x101B


class Resp(IntEnum):
    """Response codes (ISO 15740 table 27)."""

    OK = 0x2001
    GeneralError = 0x2002
    SessionNotOpen = 0x2003
    InvalidTransactionID = 0x2004
    OperationNotSupported = 0x2005
    ParameterNotSupported = 0x2006
    IncompleteTransfer = 0x2007
    InvalidStorageID = 0x2008
    InvalidObjectHandle = 0x2009
    DevicePropNotSupported = 0x200A
    InvalidObjectFormatCode = 0x200B
    StoreFull = 0x200C
    ObjectWriteProtected = 0x200D
    StoreReadOnly = 0x200E
    AccessDenied = 0x200F
    NoThumbnailPresent = 0x2010
    SelfTestFailed = 0x2011
    PartialDeletion = 0x2012
    StoreNotAvailable = 0x2013
    SpecificationByFormatUnsupported = 0x2014
    NoValidObjectInfo = 0x2015
    InvalidCodeFormat = 0x2016
    UnknownVendorCode = 0x2017
    CaptureAlreadyTerminated = 0x2018
    DeviceBusy = 0x2019
    InvalidParentObject = 0x201A
    InvalidDevicePropFormat = 0x201B
    InvalidDevicePropValue = 0x201C
    InvalidParameter = 0x201D
    SessionAlreadyOpen = 0x201E
    TransactionCancelled = 0x201F


class Event(IntEnum):
    """Event codes (ISO 15740 table 30)."""

    CancelTransaction = 0x4001
    ObjectAdded = 0x4002
    ObjectRemoved = 0x4003
    StoreAdded = 0x4004
    StoreRemoved = 0x4005
    DevicePropChanged = 0x4006
    ObjectInfoChanged = 0x4007
    DeviceInfoChanged = 0x4008
    RequestObjectTransfer = 0x4009
    StoreFull = 0x400A
    DeviceReset = 0x400B
    StorageInfoChanged = 0x400C
    CaptureComplete = 0x400D
    UnreportedStatus = 0x400E


class Prop(IntEnum):
    """Device property codes used by gonio (ISO 15740 table 32)."""

    BatteryLevel = 0x5001
    WhiteBalance = 0x5005
    FNumber = 0x5007            # UINT16, f-number x 100
    FocalLength = 0x5008
    ExposureTime = 0x500D       # UINT32, seconds x 10000
    ExposureProgramMode = 0x500E
    ExposureIndex = 0x500F      # UINT16, ISO


class DataType(IntEnum):
    INT8 = 0x0001
    UINT8 = 0x0002
    INT16 = 0x0003
    UINT16 = 0x0004
    INT32 = 0x0005
    UINT32 = 0x0006
    INT64 = 0x0007
    UINT64 = 0x0008
    STR = 0xFFFF


#: object format codes (ISO 15740 table 20, DNG from PTP 1.1; Canon vendor codes as in
#: libgphoto2's ptp.h: 0xB101 CRW (Sony bodies reuse it for ARW), 0xB103 "CRW3" = CR2, 0xB108 CR3)
OBJECT_FORMATS = {0x3000: "undefined", 0x3801: "jpeg", 0x3802: "tiff-ep", 0x380D: "tiff",
                  0x3811: "dng", 0xB101: "crw/arw", 0xB103: "cr2", 0xB108: "cr3"}

_INT_FORMATS = {DataType.INT8: "b", DataType.UINT8: "B", DataType.INT16: "h",
                DataType.UINT16: "H", DataType.INT32: "i", DataType.UINT32: "I",
                DataType.INT64: "q", DataType.UINT64: "Q"}


def response_name(code: int) -> str:
    try:
        return Resp(code).name
    except ValueError:
        return f"vendor/unknown response 0x{code:04X}"


def op_name(code: int) -> str:
    try:
        return Op(code).name
    except ValueError:
        return f"operation 0x{code:04X}"


class PtpError(DeviceError):
    """The camera answered an operation with a response code other than OK.

    ``code`` is the response code (int), ``meaning`` its ISO 15740 name, ``op`` the operation.
    """

    def __init__(self, code: int, op: int, *, device: str = "") -> None:
        self.op = op
        super().__init__(f"0x{code:04X}", f"{response_name(code)} (to {op_name(op)})", device=device)
        self.code = code


# -- containers -------------------------------------------------------------------------------
@dataclass(frozen=True)
class Container:
    """One decoded PTP container."""

    type: int
    code: int
    transaction_id: int
    params: tuple[int, ...] = ()
    payload: bytes = b""


def encode_container(ctype: int, code: int, transaction_id: int, params: tuple[int, ...] = (),
                     payload: bytes = b"") -> bytes:
    """Encode a container. Command/response/event take ``params`` (<= 5 uint32), data ``payload``.

    Raises
    ------
    ValueError
        More than five parameters, a parameter outside uint32, or both params and payload.
    """
    if len(params) > MAX_PARAMS:
        raise ValueError(f"a PTP container carries at most {MAX_PARAMS} params, got {len(params)}")
    if params and payload:
        raise ValueError("a container has either params (command/response/event) or a payload (data)")
    for p in params:
        if not 0 <= p <= 0xFFFFFFFF:
            raise ValueError(f"PTP params are uint32, got {p}")
    body = struct.pack(f"<{len(params)}I", *params) if params else bytes(payload)
    return HEADER.pack(HEADER_SIZE + len(body), ctype, code, transaction_id) + body


def decode_container(buf: bytes | bytearray | memoryview, *, device: str = "") -> Container:
    """Decode one complete container (header length must match the bytes given).

    Raises
    ------
    ProtocolError
        Too short, length field disagreeing with the buffer, unknown container type, or a
        parameter block that is not whole uint32s.
    """
    raw = bytes(buf)
    if len(raw) < HEADER_SIZE:
        raise ProtocolError(f"PTP container shorter than its {HEADER_SIZE}-byte header",
                            device=device, raw=raw[:64])
    length, ctype, code, tid = HEADER.unpack_from(raw)
    if length != len(raw):
        raise ProtocolError(f"PTP container length field {length} != {len(raw)} bytes received",
                            device=device, raw=raw[:64])
    if ctype not in ContainerType.__members__.values():
        raise ProtocolError(f"unknown PTP container type {ctype}", device=device, raw=raw[:64])
    body = raw[HEADER_SIZE:]
    if ctype == ContainerType.DATA:
        return Container(ctype, code, tid, (), body)
    if len(body) % 4 or len(body) > 4 * MAX_PARAMS:
        raise ProtocolError(f"PTP {ContainerType(ctype).name.lower()} has a {len(body)}-byte "
                            "parameter block (want 0..5 uint32)", device=device, raw=raw)
    return Container(ctype, code, tid, struct.unpack(f"<{len(body) // 4}I", body))


# -- dataset primitives -----------------------------------------------------------------------
class Reader:
    """Cursor over a dataset; every read checks bounds and raises ``ProtocolError``."""

    def __init__(self, data: bytes, what: str = "dataset", device: str = "") -> None:
        self.data, self.pos, self.what, self.device = data, 0, what, device

    def _take(self, n: int) -> bytes:
        if self.pos + n > len(self.data):
            raise ProtocolError(f"{self.what} ends early (need {n} bytes at offset {self.pos}, "
                                f"have {len(self.data)})", device=self.device)
        out = self.data[self.pos:self.pos + n]
        self.pos += n
        return out

    def value(self, datatype: int) -> int | str:
        if datatype == DataType.STR:
            return self.string()
        fmt = _INT_FORMATS.get(datatype)
        if fmt is None:
            raise ProtocolError(f"{self.what}: unsupported data type 0x{datatype:04X}", device=self.device)
        return struct.unpack("<" + fmt, self._take(struct.calcsize(fmt)))[0]

    def u8(self) -> int:
        return self._take(1)[0]

    def u16(self) -> int:
        return struct.unpack("<H", self._take(2))[0]

    def u32(self) -> int:
        return struct.unpack("<I", self._take(4))[0]

    def u16_array(self) -> tuple[int, ...]:
        n = self.u32()
        return struct.unpack(f"<{n}H", self._take(2 * n))

    def u32_array(self) -> tuple[int, ...]:
        n = self.u32()
        return struct.unpack(f"<{n}I", self._take(4 * n))

    def string(self) -> str:
        n = self.u8()
        if n == 0:
            return ""
        raw = self._take(2 * n)
        try:
            text = raw.decode("utf-16-le")
        except UnicodeDecodeError:
            raise ProtocolError(f"{self.what}: string is not UCS-2", device=self.device,
                                raw=raw) from None
        return text[:-1] if text.endswith("\x00") else text


def pack_string(text: str) -> bytes:
    """PTP string: count byte (characters including the NUL), UCS-2 LE characters, NUL."""
    if not text:
        return b"\x00"
    if len(text) > 254:
        raise ValueError(f"PTP strings hold at most 254 characters, got {len(text)}")
    return bytes([len(text) + 1]) + (text + "\x00").encode("utf-16-le")


def pack_value(datatype: int, value: int | str) -> bytes:
    """Encode one property value of ``datatype``."""
    if datatype == DataType.STR:
        return pack_string(str(value))
    fmt = _INT_FORMATS.get(datatype)
    if fmt is None:
        raise ValueError(f"unsupported PTP data type 0x{datatype:04X}")
    try:
        return struct.pack("<" + fmt, int(value))
    except struct.error as exc:
        raise ValueError(f"value {value} does not fit PTP type {DataType(datatype).name}: {exc}") from None


# -- datasets ---------------------------------------------------------------------------------
@dataclass(frozen=True)
class DeviceInfo:
    """The GetDeviceInfo dataset (ISO 15740 5.5.1)."""

    standard_version: int
    vendor_extension_id: int
    vendor_extension_version: int
    vendor_extension_desc: str
    functional_mode: int
    operations: tuple[int, ...]
    events: tuple[int, ...]
    properties: tuple[int, ...]
    capture_formats: tuple[int, ...]
    image_formats: tuple[int, ...]
    manufacturer: str
    model: str
    device_version: str
    serial_number: str


def parse_device_info(data: bytes, *, device: str = "") -> DeviceInfo:
    """Decode the GetDeviceInfo data phase; ``ProtocolError`` if it is truncated or malformed."""
    r = Reader(data, "DeviceInfo", device)
    return DeviceInfo(r.u16(), r.u32(), r.u16(), r.string(), r.u16(), r.u16_array(),
                      r.u16_array(), r.u16_array(), r.u16_array(), r.u16_array(), r.string(),
                      r.string(), r.string(), r.string())


@dataclass(frozen=True)
class PropDesc:
    """A DevicePropDesc dataset (ISO 15740 5.5.2).

    ``form`` is ``"none"``, ``"range"`` (``minimum``, ``maximum``, ``step``) or ``"enum"``
    (``values``). Values are raw device units (ExposureTime in 1/10000 s, FNumber x 100).
    """

    code: int
    datatype: int
    writable: bool
    factory_default: int | str
    current: int | str
    form: str
    values: tuple[int | str, ...] = ()
    minimum: int | None = None
    maximum: int | None = None
    step: int | None = None


def parse_prop_desc(data: bytes, *, device: str = "") -> PropDesc:
    """Decode a GetDevicePropDesc data phase (values in the property's raw device units)."""
    r = Reader(data, "DevicePropDesc", device)
    code, dtype, getset = r.u16(), r.u16(), r.u8()
    factory, current = r.value(dtype), r.value(dtype)
    flag = r.u8()
    if flag == 0:
        return PropDesc(code, dtype, bool(getset), factory, current, "none")
    if flag == 1:
        lo, hi, step = r.value(dtype), r.value(dtype), r.value(dtype)
        return PropDesc(code, dtype, bool(getset), factory, current, "range", minimum=lo,
                        maximum=hi, step=step)
    if flag == 2:
        n = r.u16()
        return PropDesc(code, dtype, bool(getset), factory, current, "enum",
                        values=tuple(r.value(dtype) for _ in range(n)))
    raise ProtocolError(f"DevicePropDesc 0x{code:04X}: unknown form flag {flag}", device=device)


@dataclass(frozen=True)
class ObjectInfo:
    """The ObjectInfo dataset (ISO 15740 5.5.3); sizes in bytes, pixel sizes in pixels."""

    storage_id: int
    object_format: int
    protection_status: int
    compressed_size: int
    thumb_format: int
    thumb_compressed_size: int
    thumb_width: int
    thumb_height: int
    image_width: int
    image_height: int
    image_bit_depth: int
    parent_object: int
    association_type: int
    association_desc: int
    sequence_number: int
    filename: str
    capture_date: str
    modification_date: str
    keywords: str

    @property
    def format_name(self) -> str:
        return OBJECT_FORMATS.get(self.object_format, f"0x{self.object_format:04X}")


def parse_object_info(data: bytes, *, device: str = "") -> ObjectInfo:
    """Decode a GetObjectInfo data phase (sizes in bytes, image size in pixels)."""
    r = Reader(data, "ObjectInfo", device)
    return ObjectInfo(r.u32(), r.u16(), r.u16(), r.u32(), r.u16(), r.u32(), r.u32(), r.u32(),
                      r.u32(), r.u32(), r.u32(), r.u32(), r.u16(), r.u32(), r.u32(), r.string(),
                      r.string(), r.string(), r.string())


# -- session over pyusb -----------------------------------------------------------------------
class _Stall(Exception):
    """An endpoint halted (EPIPE); handled inside :class:`PtpSession`."""


class ShortRead(ProtocolError):
    """A data phase ended (short packet) before the length its header announced."""


@dataclass
class Response:
    """Result of one transaction: response ``code``, its ``params``, and the data phase (if any)."""

    code: int
    params: tuple[int, ...] = ()
    data: bytes | None = None


#: operations that may be repeated after a stall or short data phase without side effects
_IDEMPOTENT = {Op.GetDeviceInfo, Op.GetStorageIDs, Op.GetStorageInfo, Op.GetNumObjects,
               Op.GetObjectHandles, Op.GetObjectInfo, Op.GetObject, Op.GetThumb,
               Op.GetDevicePropDesc, Op.GetDevicePropValue, Op.SetDevicePropValue,
               Op.GetPartialObject}
#: times a broken-off download is resumed with GetPartialObject before giving up
_RESUMES = 3


class PtpSession:
    """PTP transactions over the bulk/interrupt endpoints of a claimed pyusb device.

    Parameters
    ----------
    dev : usb.core.Device
        The configured device (its still-image interface claimed).
    ep_out, ep_in, ep_event : int
        Endpoint addresses: bulk OUT, bulk IN, interrupt IN.
    max_packet : int
        ``wMaxPacketSize`` of the bulk IN endpoint, bytes (512 at high speed).
    interface : int
        bInterfaceNumber of the still-image interface (class requests are addressed to it).
    timeout_s : float
        Per-transfer timeout, seconds.
    busy_timeout_s : float
        How long to keep retrying an operation answered DeviceBusy (0x2019), seconds.
    chunk_bytes : int
        Size of each bulk read in a data phase (rounded to whole packets), bytes.
    device : str
        Device name for errors and logs.
    """

    def __init__(self, dev: Any, *, ep_out: int, ep_in: int, ep_event: int, max_packet: int = 512,
                 interface: int = 0, timeout_s: float = 5.0, busy_timeout_s: float = 10.0,
                 chunk_bytes: int = 8 << 20, device: str = "camera") -> None:
        self.dev = dev
        self.interface = interface
        self.ep_out, self.ep_in, self.ep_event = ep_out, ep_in, ep_event
        self.max_packet = max_packet
        self.timeout_s = timeout_s
        self.busy_timeout_s = busy_timeout_s
        self.device = device
        chunk = max(max_packet, chunk_bytes // max_packet * max_packet)
        self._chunk = array.array("B", bytes(chunk))
        self._event_buf = array.array("B", bytes(max(64, max_packet)))
        self._payload = bytearray()  # grows to the largest data phase seen
        self.lock = threading.RLock()  # one transaction at a time (a UI may read while capturing)
        self.session_id = 0
        self._tid = 0
        self.reopened = 0  # sessions re-opened after SessionNotOpen (for logs and tests)
        self.resumed = 0  # downloads resumed with GetPartialObject (for logs and tests)
        # payload bytes of the last data phase that broke off (stall, short packet), for resuming
        self.interrupted = b""

    # -- low-level USB, exceptions mapped -----------------------------------------------------
    def _usb(self, fn, what: str, timeout_s: float):
        try:
            return fn()
        except usb.core.USBTimeoutError:
            raise DeviceTimeout(f"USB {what} timed out", device=self.device,
                                timeout_s=timeout_s) from None
        except usb.core.USBError as exc:
            if exc.errno == errno.ENODEV or exc.backend_error_code == -4:
                raise Disconnected(f"USB device gone during {what}", device=self.device) from None
            if exc.errno == errno.EPIPE or exc.backend_error_code == -9:
                raise _Stall(what) from None
            raise ProtocolError(f"USB error during {what}: {exc}", device=self.device) from None
        except (ValueError, NotImplementedError) as exc:  # pyusb: bad endpoint, no backend support
            raise ProtocolError(f"USB {what} failed: {exc}", device=self.device) from None

    def _write(self, data: bytes) -> None:
        ms = int(self.timeout_s * 1000)
        self._usb(lambda: self.dev.write(self.ep_out, data, ms), "bulk write", self.timeout_s)
        if len(data) % self.max_packet == 0:  # a whole-packet transfer ends with a ZLP
            self._usb(lambda: self.dev.write(self.ep_out, b"", ms), "bulk write (ZLP)", self.timeout_s)

    def _read(self, buf: array.array, timeout_s: float | None = None) -> int:
        t = self.timeout_s if timeout_s is None else timeout_s
        return self._usb(lambda: self.dev.read(self.ep_in, buf, int(t * 1000)), "bulk read", t)

    def clear_stall(self) -> None:
        """Clear the halt on both bulk endpoints (after an EPIPE)."""
        for ep in (self.ep_in, self.ep_out):
            try:
                self._usb(lambda ep=ep: self.dev.clear_halt(ep), "clear halt", self.timeout_s)
            except _Stall:
                raise ProtocolError("endpoint still stalled after clear halt",
                                    device=self.device) from None

    def read_container(self, *, what: str) -> Container:
        """Read one container from bulk IN; a data container may span many transfers.

        Raises
        ------
        ProtocolError
            The data phase ended (short packet) before the length in its header.
        """
        buf = self._chunk
        n = self._read(buf)
        if n < HEADER_SIZE:
            raise ProtocolError(f"{what}: {n}-byte transfer is shorter than a PTP header",
                                device=self.device, raw=bytes(buf[:n]))
        length, ctype, code, tid = HEADER.unpack_from(buf)
        if ctype != ContainerType.DATA or length <= n:
            if length != n:
                raise ProtocolError(f"{what}: container length {length} != {n} bytes received",
                                    device=self.device, raw=bytes(buf[:min(n, 64)]))
            return decode_container(memoryview(buf)[:n], device=self.device)
        # large data phase: chunks land in a download buffer kept between transfers, so a
        # 48 MB frame does not pay for a fresh zero-filled allocation on every GetObject
        size = length - HEADER_SIZE
        if len(self._payload) < size:
            self._payload = bytearray(size)
        view = memoryview(self._payload)[:size]
        got = n - HEADER_SIZE
        view[:got] = memoryview(buf)[HEADER_SIZE:n]
        last = n
        timeout = max(self.timeout_s, 1.0)
        while got < size:
            if last % self.max_packet:  # a short packet ended the transfer early
                break
            try:
                last = self._read(buf, timeout)
            except _Stall:
                self.interrupted = bytes(view[:got])  # what arrived stays usable for a resume
                raise
            if last == 0:
                break
            take = min(last, size - got)
            view[got:got + take] = memoryview(buf)[:take]
            got += take
        if got < size:
            self.interrupted = bytes(view[:got])
            raise ShortRead(f"{what}: data phase ended after {got + HEADER_SIZE} of "
                            f"{length} bytes (short read)", device=self.device)
        if length % self.max_packet == 0:
            try:  # the terminating zero-length packet
                self._read(buf, min(self.timeout_s, 0.05))
            except DeviceTimeout:
                pass
        return Container(ctype, code, tid, (), bytes(view))

    # -- transactions -------------------------------------------------------------------------
    def transaction(self, op: int, params: tuple[int, ...] = (), data_out: bytes | None = None,
                    *, check: bool = True, retry_busy: bool = True, reopen: bool = True,
                    repeat_io: bool = True) -> Response:
        """Run one operation and return its response.

        DeviceBusy is retried with exponential back-off (10 ms doubling to 0.5 s) for up to
        ``busy_timeout_s``; SessionNotOpen re-opens the session once and repeats the operation;
        a stalled endpoint or a short data phase is cleared and, for idempotent operations and
        ``repeat_io``, repeated once.

        Raises
        ------
        PtpError
            The camera answered with a code other than OK (when ``check``).
        DeviceBusy
            Still busy after ``busy_timeout_s``.
        DeviceTimeout, Disconnected, ProtocolError
            Transfer-level failures.
        """
        with self.lock:
            return self._transaction(op, params, data_out, check, retry_busy, reopen, repeat_io)

    def _transaction(self, op: int, params: tuple[int, ...], data_out: bytes | None, check: bool,
                     retry_busy: bool, reopen: bool, repeat_io: bool) -> Response:
        deadline = time.monotonic() + self.busy_timeout_s
        delay = 0.01
        retried_io = not repeat_io
        reopened = False
        while True:
            try:
                resp = self._transaction_once(op, params, data_out)
            except DeviceTimeout:
                self.cancel(self._tid)  # drop what the camera may still send for it
                raise
            except (_Stall, ProtocolError) as exc:
                stalled = isinstance(exc, _Stall)
                if stalled:
                    self.clear_stall()
                if retried_io or op not in _IDEMPOTENT:
                    if stalled:
                        raise ProtocolError(f"{op_name(op)}: endpoint stalled ({exc}); halt cleared",
                                            device=self.device) from None
                    raise
                log.warning("%s: %s failed (%s); repeating once", self.device, op_name(op), exc)
                retried_io = True
                continue
            if resp.code == Resp.DeviceBusy and retry_busy:
                if time.monotonic() + delay > deadline:
                    raise DeviceBusy(f"{op_name(op)} still answered DeviceBusy after "
                                     f"{self.busy_timeout_s:g} s", device=self.device)
                time.sleep(delay)
                delay = min(2 * delay, 0.5)
                continue
            if resp.code == Resp.SessionNotOpen and reopen and not reopened and self.session_id \
                    and op not in (Op.OpenSession, Op.GetDeviceInfo):
                log.warning("%s: session closed by the camera; re-opening", self.device)
                self.open(self.session_id)
                self.reopened += 1
                reopened = True
                continue
            if check and resp.code != Resp.OK:
                raise PtpError(resp.code, op, device=self.device)
            return resp

    def _transaction_once(self, op: int, params: tuple[int, ...], data_out: bytes | None) -> Response:
        if op == Op.OpenSession or (op == Op.GetDeviceInfo and not self.session_id):
            # ISO 15740: outside a session (OpenSession itself, GetDeviceInfo before it) the
            # TransactionID is 0; inside one the ids count from 1
            tid = 0
        else:
            self._tid = 1 if self._tid >= 0xFFFFFFFE else self._tid + 1
            tid = self._tid
        self._write(encode_container(ContainerType.COMMAND, op, tid, params))
        if data_out is not None:
            self._write(encode_container(ContainerType.DATA, op, tid, payload=data_out))
        data = None
        short: ShortRead | None = None
        for _ in range(4):  # skip stale containers left by an earlier timed-out transaction
            try:
                c = self.read_container(what=op_name(op))
            except ShortRead as exc:
                short = exc  # the response still follows; read it to stay in step
                continue
            if c.transaction_id != tid and op != Op.OpenSession:
                log.warning("%s: dropping stale container for transaction %d (expected %d)",
                            self.device, c.transaction_id, tid)
                continue
            if c.type == ContainerType.DATA:
                data = c.payload
                continue
            if c.type != ContainerType.RESPONSE:
                raise ProtocolError(f"{op_name(op)}: unexpected {ContainerType(c.type).name} "
                                    "container on bulk IN", device=self.device)
            if short is not None:
                raise short
            return Response(c.code, c.params, data)
        raise ProtocolError(f"{op_name(op)}: no response container for transaction {tid}",
                            device=self.device)

    def cancel(self, transaction_id: int) -> bool:
        """Still-image class Cancel Request (0x64) for ``transaction_id``, then Get Device Status
        (0x67) until the camera is no longer busy (USB Still Image Capture Device Definition,
        5.2.1 and 5.2.4). Best effort after a timeout; returns True if the camera reported OK.
        """
        ms = max(1, int(min(self.timeout_s, 1.0) * 1000))
        try:
            self.dev.ctrl_transfer(0x21, 0x64, 0, self.interface,
                                   struct.pack("<HI", Event.CancelTransaction, transaction_id), ms)
            for _ in range(50):
                status = self.dev.ctrl_transfer(0xA1, 0x67, 0, self.interface, 64, ms)
                if len(status) >= 4 and struct.unpack_from("<H", bytes(status), 2)[0] != Resp.DeviceBusy:
                    return struct.unpack_from("<H", bytes(status), 2)[0] == Resp.OK
                time.sleep(0.01)
        except (usb.core.USBError, ValueError, NotImplementedError) as exc:
            log.warning("%s: cancel of transaction %d failed: %s", self.device, transaction_id, exc)
        return False

    def open(self, session_id: int = 1) -> None:
        """OpenSession (transaction id 0); an already open session is accepted."""
        self._tid = 0
        resp = self.transaction(Op.OpenSession, (session_id,), check=False, reopen=False)
        if resp.code not in (Resp.OK, Resp.SessionAlreadyOpen):
            raise PtpError(resp.code, Op.OpenSession, device=self.device)
        self.session_id = session_id

    def close(self) -> None:
        """CloseSession; errors are ignored (the device may be gone)."""
        if self.session_id:
            try:
                self.transaction(Op.CloseSession, reopen=False, retry_busy=False)
            except (DeviceError, DeviceTimeout, Disconnected, ProtocolError, DeviceBusy):
                pass
            self.session_id = 0

    # -- events -------------------------------------------------------------------------------
    def read_event(self, timeout_s: float) -> Container | None:
        """One event container from the interrupt endpoint, or None if none within ``timeout_s``."""
        ms = max(1, int(timeout_s * 1000))
        buf = self._event_buf
        with self.lock:
            return self._read_event(buf, ms, timeout_s)

    def _read_event(self, buf: array.array, ms: int, timeout_s: float) -> Container | None:
        try:
            n = self._usb(lambda: self.dev.read(self.ep_event, buf, ms), "interrupt read", timeout_s)
        except DeviceTimeout:
            return None
        except _Stall:
            self._usb(lambda: self.dev.clear_halt(self.ep_event), "clear halt", self.timeout_s)
            return None
        c = decode_container(memoryview(buf)[:n], device=self.device)
        if c.type != ContainerType.EVENT:
            raise ProtocolError(f"non-event container type {c.type} on the interrupt endpoint",
                                device=self.device)
        return c

    # -- operations ---------------------------------------------------------------------------
    def get_device_info(self) -> DeviceInfo:
        """GetDeviceInfo (0x1001); allowed outside a session."""
        return parse_device_info(self.transaction(Op.GetDeviceInfo).data or b"", device=self.device)

    def get_prop_desc(self, prop: int) -> PropDesc:
        """GetDevicePropDesc (0x1014): type, current value and allowed values of ``prop``."""
        return parse_prop_desc(self.transaction(Op.GetDevicePropDesc, (prop,)).data or b"",
                               device=self.device)

    def get_prop_value(self, prop: int, datatype: int) -> int | str:
        """GetDevicePropValue (0x1015), decoded as ``datatype``; raw device units
        (ExposureTime in 1/10000 s, FNumber x 100)."""
        data = self.transaction(Op.GetDevicePropValue, (prop,)).data or b""
        return Reader(data, f"value of 0x{prop:04X}", self.device).value(datatype)

    def set_prop_value(self, prop: int, datatype: int, value: int | str) -> None:
        """SetDevicePropValue (0x1016) with ``value`` (raw device units) in the data phase."""
        self.transaction(Op.SetDevicePropValue, (prop,), pack_value(datatype, value))

    def initiate_capture(self, storage_id: int = 0, object_format: int = 0) -> None:
        """InitiateCapture (0x100E); the result arrives as ObjectAdded / CaptureComplete events."""
        self.transaction(Op.InitiateCapture, (storage_id, object_format))

    def get_object_handles(self, storage_id: int = 0xFFFFFFFF) -> tuple[int, ...]:
        """GetObjectHandles (0x1007) of all objects on ``storage_id`` (default: every store)."""
        data = self.transaction(Op.GetObjectHandles, (storage_id, 0, 0)).data or b""
        return Reader(data, "ObjectHandles", self.device).u32_array()

    def get_object_info(self, handle: int) -> ObjectInfo:
        """GetObjectInfo (0x1008) of ``handle``."""
        return parse_object_info(self.transaction(Op.GetObjectInfo, (handle,)).data or b"",
                                 device=self.device)

    def get_object(self, handle: int, size: int | None = None) -> bytes:
        """GetObject (0x1009): the object's bytes (a data phase of many transfers).

        With ``size`` (its ObjectCompressedSize, bytes) a data phase that breaks off part way (an
        endpoint stall, a short packet) is finished with GetPartialObject from the first byte
        missing, up to ``_RESUMES`` times, instead of starting a large download over; the camera
        must offer GetPartialObject (0x101B). Without ``size``, or when nothing had arrived, the
        whole GetObject is repeated once.

        Raises
        ------
        ProtocolError
            The download still broke off after the resumes, or the camera sent more than ``size``.
        """
        if size is None:
            return self.transaction(Op.GetObject, (handle,)).data or b""
        self.interrupted = b""
        try:
            return self.transaction(Op.GetObject, (handle,), repeat_io=False).data or b""
        except ProtocolError as exc:
            data = bytearray(self.interrupted)
            if not data:
                log.warning("%s: GetObject %d failed (%s); repeating once", self.device, handle, exc)
                return self.transaction(Op.GetObject, (handle,), repeat_io=False).data or b""
        for _ in range(_RESUMES):
            log.warning("%s: download of object %d broke off after %d of %d bytes; resuming with "
                        "GetPartialObject", self.device, handle, len(data), size)
            self.resumed += 1
            self.interrupted = b""
            try:
                data += self.get_partial_object(handle, len(data), size - len(data))
            except ProtocolError:
                if not self.interrupted:
                    raise
                data += self.interrupted
                continue
            if len(data) > size:
                raise ProtocolError(f"object {handle}: resumed download gave {len(data)} bytes, "
                                    f"ObjectInfo says {size}", device=self.device)
            return bytes(data)
        raise ProtocolError(f"object {handle}: download broke off {_RESUMES + 1} times "
                            f"({len(data)} of {size} bytes)", device=self.device)

    def get_partial_object(self, handle: int, offset: int, max_bytes: int) -> bytes:
        """GetPartialObject (0x101B): up to ``max_bytes`` bytes of ``handle`` from byte ``offset``
        (no repeat on a broken data phase: :meth:`get_object` resumes from what arrived).

        Raises
        ------
        ProtocolError
            The response's byte count disagrees with the data phase.
        """
        resp = self.transaction(Op.GetPartialObject, (handle, offset, max_bytes), repeat_io=False)
        data = resp.data or b""
        if resp.params and resp.params[0] != len(data):
            raise ProtocolError(f"GetPartialObject of {handle}: response says {resp.params[0]} "
                                f"bytes, data phase had {len(data)}", device=self.device)
        return data

    def delete_object(self, handle: int) -> None:
        """DeleteObject (0x100B) of ``handle``."""
        self.transaction(Op.DeleteObject, (handle, 0))
