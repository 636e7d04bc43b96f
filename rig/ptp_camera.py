"""Tethered still camera over PTP/USB (ISO 15740) through pyusb.

``PtpCamera`` finds the camera by USB vendor/product id, claims its still-image interface
(class 6), opens a PTP session and reads the DeviceInfo. Settings use the standard properties
ExposureTime (0x500D, 1/10000 s), ExposureIndex (0x500F, ISO) and FNumber (0x5007, x100); a
requested value snaps to the nearest value the camera enumerates in its DevicePropDesc.

``capture()`` runs the tethered sequence: InitiateCapture -> ObjectAdded (+ CaptureComplete) on
the interrupt endpoint -> GetObjectInfo (file name, size) -> GetObject (checked against
ObjectCompressedSize; resumed with GetPartialObject if it breaks off part way and the camera
offers that operation) -> DeleteObject, so the card never fills. If the card is full anyway
(StoreFull), the objects already downloaded in this session are deleted and the capture repeated.

Many DSLR bodies capture only through vendor operations (Canon EOS 0x9xxx, Nikon 0x90C0); those
are served by another :class:`~rig.device.Camera` implementation (libgphoto2), registered as its
own driver, rather than by vendor branches here.
"""
from __future__ import annotations

import dataclasses
import errno
import logging
import math
import re
import time
from typing import Any

import usb.core
import usb.util

from .device import Camera, Frame, reading
from .errors import DeviceError, DeviceTimeout, Disconnected, LimitError, ProtocolError, RigError
from .ptp import (OBJECT_FORMATS, DataType, DeviceInfo, Event, Op, Prop, PropDesc, PtpError,
                  PtpSession, Resp)

log = logging.getLogger("gonio.rig.ptp")

STILL_IMAGE_CLASS = 6
_RAW_FORMATS = {0x3811, 0xB101, 0xB103, 0x3802}
_PORT = re.compile(r"^usb:([0-9a-fA-F]{1,4}):([0-9a-fA-F]{1,4})$")
#: a request may lie this far (a third of a stop) outside the camera's range before LimitError
_RANGE_SLACK = 2 ** (1 / 3)


def parse_port(port: str) -> tuple[int, int]:
    """``"usb:04a9:32b4"`` -> ``(0x04A9, 0x32B4)``.

    Raises
    ------
    ValueError
        If ``port`` is not ``usb:VID:PID`` with hex ids.
    """
    m = _PORT.match(port.strip()) if isinstance(port, str) else None
    if m is None:
        raise ValueError(f"camera port must be 'usb:VID:PID' with hex ids (e.g. 'usb:04a9:32b4'), "
                         f"got {port!r}")
    return int(m.group(1), 16), int(m.group(2), 16)


def libusb_backend():
    """The libusb-1.0 backend shipped by the ``libusb-package`` wheel."""
    try:
        import libusb_package
    except ImportError:
        raise Disconnected("no libusb available: pip install libusb-package") from None
    backend = libusb_package.get_libusb1_backend()
    if backend is None:
        raise Disconnected("libusb-package is installed but its libusb could not be loaded")
    return backend


def _usable(desc: PropDesc) -> tuple[int, ...]:
    """Enumerated values that are real settings: positive, and not the all-ones sentinels some
    bodies list for bulb / time / auto (0xFFFFFFFF, 0xFFFFFFFD, 0xFFFF ...)."""
    top = {DataType.UINT16: 0xFFFF, DataType.UINT32: 0xFFFFFFFF}.get(desc.datatype)
    return tuple(v for v in desc.values
                 if isinstance(v, int) and v > 0 and (top is None or v < top - 15))


def snap(desc: PropDesc, raw: float, *, log_scale: bool = True) -> int:
    """The allowed raw value of ``desc`` nearest to ``raw`` (in log space for exposure-like
    properties, where steps are ratios), clamped to a range form's limits."""
    if desc.form == "enum":
        values = [v for v in desc.values if isinstance(v, int) and (v > 0 or not log_scale)]
        if not values:
            raise ProtocolError(f"property 0x{desc.code:04X} enumerates no usable values")
        key = (lambda v: abs(math.log(v / raw))) if log_scale else (lambda v: abs(v - raw))
        return min(values, key=key)
    if desc.form == "range":
        lo, hi, step = int(desc.minimum), int(desc.maximum), int(desc.step or 1)
        return int(min(hi, max(lo, lo + round((raw - lo) / step) * step)))
    return int(round(raw))


class PtpCamera(Camera):
    """A PTP camera on USB.

    Parameters
    ----------
    name : str
        Role in the rig (``"camera"``).
    vendor_id, product_id : int
        USB ids.
    backend : usb.backend.IBackend, optional
        pyusb backend (a simulator, or None for libusb from ``libusb-package``).
    timeout_s : float
        Per-transfer timeout, seconds.
    busy_timeout_s : float
        How long DeviceBusy answers are retried (with back-off), seconds.
    capture_timeout_s : float
        Time allowed for ObjectAdded after InitiateCapture, on top of the exposure, seconds.
    keep_on_camera : bool
        Leave each image on the card after download (it is then deleted only when the card is full).
    session_id : int
        PTP session id to open.
    chunk_bytes : int
        Bulk read size during downloads, bytes.
    """

    def __init__(self, name: str, vendor_id: int, product_id: int, *, backend: Any = None,
                 timeout_s: float = 5.0, busy_timeout_s: float = 10.0,
                 capture_timeout_s: float = 30.0, keep_on_camera: bool = False,
                 session_id: int = 1, chunk_bytes: int = 8 << 20) -> None:
        super().__init__(name)
        for arg, value in (("timeout_s", timeout_s), ("busy_timeout_s", busy_timeout_s),
                           ("capture_timeout_s", capture_timeout_s)):
            if not value > 0:
                raise ValueError(f"{arg} must be > 0 seconds, got {value!r}")
        if not 0 < session_id <= 0xFFFFFFFF:
            raise ValueError(f"session_id must be a non-zero uint32, got {session_id}")
        self.vendor_id, self.product_id = vendor_id, product_id
        self.backend = backend
        self.timeout_s = timeout_s
        self.busy_timeout_s = busy_timeout_s
        self.capture_timeout_s = capture_timeout_s
        self.keep_on_camera = keep_on_camera
        self.session_id = session_id
        self.chunk_bytes = chunk_bytes
        self.session: PtpSession | None = None
        self.info: DeviceInfo | None = None
        self._dev: Any = None
        self._descs: dict[int, PropDesc] = {}
        self._values: dict[int, int] = {}
        self._kept: list[int] = []  # downloaded handles left on the card

    @property
    def port(self) -> str:
        """The rig-file port, ``usb:VID:PID`` (hex)."""
        return f"usb:{self.vendor_id:04x}:{self.product_id:04x}"

    @classmethod
    def from_config(cls, name: str, section: dict[str, Any], *, usb_backend: Any = None,
                    **context: Any) -> "PtpCamera":
        """Build from a rig-file section: ``port = "usb:VID:PID"`` plus optional ``timeout_s``,
        ``busy_timeout_s``, ``capture_timeout_s``, ``keep_on_camera``, ``session_id``.
        ``usb_backend`` (context) is a pyusb backend; None uses libusb."""
        from .rig import driver_options
        allowed = {"timeout_s", "busy_timeout_s", "capture_timeout_s", "keep_on_camera", "session_id"}
        kwargs = driver_options(name, section, "ptp", allowed)
        vid, pid = parse_port(section["port"])
        return cls(name, vid, pid, backend=usb_backend, **kwargs)

    # -- link ---------------------------------------------------------------------------------
    def _usb_error(self, exc: Exception, what: str) -> RigError:
        if isinstance(exc, usb.core.USBTimeoutError):
            return DeviceTimeout(f"{what}: USB timeout", device=self.name, timeout_s=self.timeout_s)
        code = getattr(exc, "errno", None)
        if code == errno.ENODEV:
            return Disconnected(f"{what}: the camera is gone", device=self.name)
        if code == errno.EACCES:
            return Disconnected(f"{what}: no permission for {self.port} (add a udev rule giving "
                                "your user access to the camera)", device=self.name)
        if code == errno.EBUSY:
            return Disconnected(f"{what}: the still-image interface is claimed by another program "
                                "(e.g. gvfs-gphoto2-volume-monitor); stop it and reconnect",
                                device=self.name)
        return ProtocolError(f"{what}: {exc}", device=self.name)

    def connect(self) -> None:
        """Find the camera by VID:PID, claim its still-image interface, open a session and read
        the device info and the exposure, ISO and aperture settings."""
        self._release()
        backend = self.backend if self.backend is not None else libusb_backend()
        try:
            dev = usb.core.find(idVendor=self.vendor_id, idProduct=self.product_id, backend=backend)
        except (usb.core.USBError, usb.core.NoBackendError) as exc:
            raise self._usb_error(exc, "USB enumeration") from None
        if dev is None:
            raise Disconnected(f"no USB device {self.port} found (is the camera on, in PTP mode, "
                               "and plugged in?)", device=self.name)
        try:
            try:
                cfg = dev.get_active_configuration()
            except usb.core.USBError:
                dev.set_configuration()
                cfg = dev.get_active_configuration()
            intf = usb.util.find_descriptor(cfg, bInterfaceClass=STILL_IMAGE_CLASS)
            if intf is None:
                raise Disconnected(f"USB device {self.port} has no still-image (PTP) interface; "
                                   "set the camera's USB mode to PTP", device=self.name)
            try:
                if dev.is_kernel_driver_active(intf.bInterfaceNumber):
                    dev.detach_kernel_driver(intf.bInterfaceNumber)
            except NotImplementedError:  # backends without kernel drivers
                pass
            usb.util.claim_interface(dev, intf)
            eps = {}
            for ep in intf:
                kind = usb.util.endpoint_type(ep.bmAttributes)
                out = usb.util.endpoint_direction(ep.bEndpointAddress) == usb.util.ENDPOINT_OUT
                eps[(kind, out)] = ep
            bulk_out = eps.get((usb.util.ENDPOINT_TYPE_BULK, True))
            bulk_in = eps.get((usb.util.ENDPOINT_TYPE_BULK, False))
            event_in = eps.get((usb.util.ENDPOINT_TYPE_INTR, False))
            if bulk_out is None or bulk_in is None or event_in is None:
                raise ProtocolError("still-image interface lacks bulk IN/OUT or interrupt IN "
                                    "endpoints", device=self.name)
        except (usb.core.USBError, ValueError, NotImplementedError) as exc:
            # pyusb raises ValueError / NotImplementedError for descriptors or backend calls it
            # cannot serve; like USBError they must reach the caller typed
            self._dispose(dev)
            raise self._usb_error(exc, "claiming the camera interface") from None
        except BaseException:
            self._dispose(dev)
            raise
        self._dev = dev
        self.session = PtpSession(dev, ep_out=bulk_out.bEndpointAddress,
                                  ep_in=bulk_in.bEndpointAddress,
                                  ep_event=event_in.bEndpointAddress,
                                  max_packet=bulk_in.wMaxPacketSize,
                                  interface=intf.bInterfaceNumber, timeout_s=self.timeout_s,
                                  busy_timeout_s=self.busy_timeout_s, chunk_bytes=self.chunk_bytes,
                                  device=self.name)
        try:
            self.info = self.session.get_device_info()
            missing = [op.name for op in (Op.InitiateCapture, Op.GetObject, Op.GetObjectInfo)
                       if op not in self.info.operations]
            if missing:
                raise DeviceError("unsupported", f"{self.info.manufacturer} {self.info.model} does "
                                  f"not offer standard PTP {', '.join(missing)}; it needs vendor "
                                  "operations (use driver = 'gphoto2')", device=self.name)
            self.session.open(self.session_id)
            self._descs = {p: self.session.get_prop_desc(p)
                           for p in (Prop.ExposureTime, Prop.ExposureIndex, Prop.FNumber)
                           if p in self.info.properties}
            if Prop.ExposureTime not in self._descs:
                raise DeviceError("unsupported", "the camera does not expose ExposureTime "
                                  "(0x500D)", device=self.name)
            self._values = {p: int(d.current) for p, d in self._descs.items()}
            self._drain_events()
        except BaseException:
            self._release()
            raise
        self._kept = []

    @staticmethod
    def _dispose(dev: Any) -> None:
        """Release pyusb's handles on ``dev``; a device already gone has nothing to release."""
        try:
            usb.util.dispose_resources(dev)
        except usb.core.USBError:
            pass

    def _release(self) -> None:
        if self._dev is not None:
            self._dispose(self._dev)
        self._dev = self.session = None

    def close(self) -> None:
        """Close the PTP session and release the interface (safe to call twice)."""
        if self.session is not None:
            self.session.close()
        self._release()

    @property
    def connected(self) -> bool:
        return self.session is not None and self.session.session_id != 0

    def _session(self) -> PtpSession:
        if self.session is None:
            raise Disconnected("not connected; call connect() first", device=self.name)
        return self.session

    # -- settings -----------------------------------------------------------------------------
    def _set(self, prop: int, raw: float, what: str, unit: str, scale: float) -> int:
        session = self._session()
        desc = self._descs.get(prop)
        if desc is None:
            raise DeviceError("unsupported", f"the camera does not offer {what}", device=self.name)
        if not desc.writable:
            raise DeviceError("read-only", f"{what} is read-only on this camera (check the mode "
                              "dial: manual exposure is needed)", device=self.name)
        if desc.form == "enum":
            desc = dataclasses.replace(desc, values=_usable(desc))
            allowed = list(desc.values)
            if not allowed:
                raise DeviceError("unsupported", f"the camera enumerates no settable {what}",
                                  device=self.name)
        else:
            allowed = [desc.minimum, desc.maximum] if desc.form == "range" else []
        if allowed:
            lo, hi = min(allowed), max(allowed)
            if not (lo / _RANGE_SLACK <= raw <= hi * _RANGE_SLACK):
                raise LimitError(raw / scale, (lo / scale, hi / scale), unit, device=self.name,
                                 what=what)
        value = snap(desc, raw)
        if value != self._values.get(prop):
            session.set_prop_value(prop, desc.datatype, value)
        # report what the camera holds now, not what was asked
        self._values[prop] = int(session.get_prop_value(prop, desc.datatype))
        return self._values[prop]

    def _check_value(self, name: str, value: float) -> float:
        value = float(value)
        if not (math.isfinite(value) and value > 0):
            raise ValueError(f"{name} must be a positive finite number, got {value!r}")
        return value

    @property
    def exposure_s(self) -> float:
        """Exposure time the camera reports, seconds."""
        return self._values[Prop.ExposureTime] / 10000.0

    def set_exposure(self, seconds: float) -> float:
        """Set the exposure to the camera's value nearest ``seconds`` (in stops); return the
        exposure the camera reports afterwards, seconds.

        Raises
        ------
        LimitError
            ``seconds`` lies more than a third of a stop outside the camera's range.
        """
        seconds = self._check_value("seconds", seconds)
        return self._set(Prop.ExposureTime, seconds * 10000.0, "exposure time", "s", 10000.0) / 10000.0

    @property
    def exposure_values(self) -> tuple[float, ...]:
        """Exposure times the camera offers, seconds (enumerated form only)."""
        desc = self._descs.get(Prop.ExposureTime)
        return tuple(v / 10000.0 for v in _usable(desc)) if desc and desc.form == "enum" else ()

    @property
    def iso(self) -> float | None:
        """ISO (ExposureIndex) the camera reports, or None if it has no such property."""
        v = self._values.get(Prop.ExposureIndex)
        return None if v is None else float(v)

    def set_iso(self, iso: float) -> float:
        """Set the ISO (nearest offered value); return what the camera reports."""
        iso = self._check_value("iso", iso)
        return float(self._set(Prop.ExposureIndex, iso, "ISO", "ISO", 1.0))

    @property
    def fnumber(self) -> float | None:
        """Aperture f-number the camera reports, or None if it has no such property."""
        v = self._values.get(Prop.FNumber)
        return None if v is None else v / 100.0

    def set_fnumber(self, fnumber: float) -> float:
        """Set the aperture (nearest offered f-number); return what the camera reports."""
        fnumber = self._check_value("fnumber", fnumber)
        return self._set(Prop.FNumber, fnumber * 100.0, "f-number", "f/", 100.0) / 100.0

    # -- capture ------------------------------------------------------------------------------
    def _drain_events(self) -> None:
        """Handle events that arrived since the last capture: re-read settings the camera says
        changed (a turned dial), and delete objects announced by a capture whose transfer failed
        after the shutter fired, so the card does not fill."""
        session = self._session()
        changed = set()
        while (event := session.read_event(0.001)) is not None:
            if event.code == Event.DevicePropChanged and event.params:
                changed.add(event.params[0])
            elif event.code == Event.ObjectAdded and event.params and not self.keep_on_camera:
                try:
                    session.delete_object(event.params[0])
                    log.info("%s: deleted orphaned object %d", self.name, event.params[0])
                except PtpError:
                    pass
        for prop in changed & set(self._descs):
            self._values[prop] = int(session.get_prop_value(prop, self._descs[prop].datatype))

    def _free_store(self) -> None:
        """Delete the objects already downloaded (their bytes are safe on the host)."""
        session = self._session()
        for handle in self._kept:
            try:
                session.delete_object(handle)
            except PtpError as exc:
                if exc.code != Resp.InvalidObjectHandle:  # already gone is fine
                    raise
        log.info("%s: card full; deleted %d downloaded images", self.name, len(self._kept))
        self._kept = []

    def _initiate(self) -> None:
        session = self._session()
        try:
            session.initiate_capture()
        except PtpError as exc:
            if exc.code != Resp.StoreFull:
                raise
            if not self._kept:
                raise DeviceError(f"0x{Resp.StoreFull:04X}", "StoreFull: the camera's card is "
                                  "full of images gonio did not download; free the card",
                                  device=self.name) from None
            self._free_store()
            session.initiate_capture()

    def _wait_objects(self, timeout_s: float) -> list[int]:
        """Handles from ObjectAdded events, up to CaptureComplete (or a short grace after the
        first object, for bodies that do not send CaptureComplete)."""
        session = self._session()
        deadline = time.monotonic() + timeout_s
        handles: list[int] = []
        while True:
            remaining = deadline - time.monotonic()
            if remaining <= 0:
                if handles:
                    return handles
                raise DeviceTimeout("no ObjectAdded event after InitiateCapture", device=self.name,
                                    timeout_s=timeout_s)
            event = session.read_event(min(remaining, 0.25) if handles else remaining)
            if event is None:
                if handles:
                    return handles
                continue
            if event.code == Event.ObjectAdded and event.params:
                handles.append(event.params[0])
                deadline = min(deadline, time.monotonic() + 1.0)
            elif event.code == Event.CaptureComplete and handles:
                return handles
            elif event.code == Event.StoreFull:
                raise DeviceError(f"0x{Event.StoreFull:04X}", "StoreFull event during capture",
                                  device=self.name)

    def _download(self, handle: int, size: int) -> bytes:
        session = self._session()
        resumable = self.info is not None and Op.GetPartialObject in self.info.operations
        for attempt in (1, 2):
            # a download broken off part way resumes where it stopped when the camera allows
            data = session.get_object(handle, size if resumable else None)
            if len(data) == size:
                return data
            log.warning("%s: object %d arrived with %d bytes, ObjectInfo says %d (attempt %d)",
                        self.name, handle, len(data), size, attempt)
        raise ProtocolError(f"object {handle} downloaded with {len(data)} bytes but ObjectInfo "
                            f"reports ObjectCompressedSize {size} (damaged transfer)",
                            device=self.name)

    def capture(self) -> Frame:
        """Take one picture and return the camera's file with the settings it reports."""
        session = self._session()
        self._drain_events()
        exposure, iso, fnumber = self.exposure_s, self.iso, self.fnumber
        self._initiate()
        handles = self._wait_objects(self.capture_timeout_s + exposure)
        stamp = time.time()
        infos = {h: session.get_object_info(h) for h in handles}
        # RAW+JPEG bodies add two objects: keep the raw one
        handle = next((h for h in handles if infos[h].object_format in _RAW_FORMATS), handles[0])
        info = infos[handle]
        try:
            data = self._download(handle, info.compressed_size)
        except RigError:
            # the shot exists only on the card now: leave it there rather than lose it
            log.error("%s: download of %s failed; it stays on the camera", self.name, info.filename)
            raise
        if self.keep_on_camera:
            self._kept.extend(handles)
        else:
            for h in handles:
                session.delete_object(h)
        return Frame(data=data, filename=info.filename, exposure_s=exposure, iso=iso,
                     fnumber=fnumber, timestamp=stamp,
                     metadata={"handle": handle, "object_format": info.format_name,
                               "size": info.compressed_size, "capture_date": info.capture_date,
                               "width": info.image_width, "height": info.image_height,
                               "bit_depth": info.image_bit_depth})

    # -- state --------------------------------------------------------------------------------
    def read(self) -> dict[str, dict[str, Any]]:
        session = self._session()
        for prop, desc in self._descs.items():
            self._values[prop] = int(session.get_prop_value(prop, desc.datatype))
        return {"exposure_s": reading(self.exposure_s, "s"), "iso": reading(self.iso, "ISO"),
                "fnumber": reading(self.fnumber, "f/")}

    def describe(self) -> dict[str, Any]:
        out: dict[str, Any] = {"driver": "ptp", "port": self.port, "units": {"exposure": "s"}}
        if self.info is not None:
            out.update(manufacturer=self.info.manufacturer, model=self.info.model,
                       firmware=self.info.device_version, serial_number=self.info.serial_number,
                       ptp_version=self.info.standard_version / 100.0,
                       image_formats=[OBJECT_FORMATS.get(f, f"0x{f:04X}")
                                      for f in self.info.image_formats])
        for key, prop, scale in (("exposure_values_s", Prop.ExposureTime, 10000.0),
                                 ("iso_values", Prop.ExposureIndex, 1.0),
                                 ("fnumber_values", Prop.FNumber, 100.0)):
            desc = self._descs.get(prop)
            if desc is not None and desc.form == "enum":
                out[key] = [v / scale for v in _usable(desc)]
        return out
