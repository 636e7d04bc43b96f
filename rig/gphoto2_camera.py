"""Tethered camera through libgphoto2 (python-gphoto2), for bodies that need vendor operations.

Most DSLR/mirrorless bodies (Canon EOS, Nikon, Sony) capture and set exposure only through
vendor PTP extensions, which libgphoto2 implements. This driver offers the same
:class:`~rig.device.Camera` API as :class:`rig.ptp_camera.PtpCamera`, so a rig file switches
between them by ``driver = "ptp"`` or ``driver = "gphoto2"``. python-gphoto2 is optional
(``pip install 'gonio[gphoto2]'``) and imported only on :meth:`Gphoto2Camera.connect`.

Settings go through libgphoto2's config widgets (``shutterspeed``, ``iso``, ``aperture`` /
``f-number``), whose choices are text such as ``"1/250"``, ``"0.3"``, ``"30"``, ``"f/8"``; a
requested value snaps to the nearest numeric choice (in stops) and the camera's reading is
reported back.
"""
from __future__ import annotations

import logging
import math
import re
import time
from typing import Any

from .device import Camera, Frame, reading
from .errors import (DeviceBusy, DeviceError, DeviceTimeout, Disconnected, LimitError,
                     ProtocolError, RigError)

log = logging.getLogger("gonio.rig.gphoto2")

_GP_PORT = re.compile(r"^usb:\d{3},\d{3}$")
_VIDPID = re.compile(r"^usb:([0-9a-fA-F]{1,4}):([0-9a-fA-F]{1,4})$")
_RANGE_SLACK = 2 ** (1 / 3)
#: config widget names to try, per setting (vendors differ)
_WIDGETS = {"exposure": ("shutterspeed", "shutterspeed2", "exptime"),
            "iso": ("iso", "isospeed"),
            "fnumber": ("f-number", "aperture", "fnumber")}


def _gphoto2():
    try:
        import gphoto2
    except ImportError:
        raise DeviceError("missing-dependency", "the gphoto2 driver needs python-gphoto2: "
                          "pip install 'gonio[gphoto2]' (and libgphoto2 on the system)") from None
    return gphoto2


def parse_choice(text: str) -> float | None:
    """Numeric value of a gphoto2 choice (``"1/250"`` -> 0.004, ``"f/5.6"`` -> 5.6, ``"30s"`` ->
    30, ``"1\\""`` -> 1); None for non-numeric ones (``"bulb"``, ``"Auto"``)."""
    t = text.strip().lower().removeprefix("f/").rstrip('s"').strip()
    try:
        if "/" in t:
            num, den = t.split("/", 1)
            return float(num) / float(den)
        return float(t)
    except (ValueError, ZeroDivisionError):
        return None


class Gphoto2Camera(Camera):
    """A camera served by libgphoto2.

    Parameters
    ----------
    name : str
        Role in the rig.
    port : str
        ``"usb:VID:PID"`` (hex, resolved to the bus/address libgphoto2 uses), a libgphoto2 port
        ``"usb:001,005"``, or ``"auto"`` for the first camera found.
    model : str, optional
        libgphoto2 model name (``"Canon EOS 5D Mark IV"``); detected when omitted.
    timeout_s : float
        Time allowed for a capture to produce its file, on top of the exposure, seconds.
    busy_timeout_s : float
        How long "camera busy" answers are retried, seconds.
    keep_on_camera : bool
        Leave each image on the card after download.
    """

    def __init__(self, name: str, port: str = "auto", *, model: str | None = None,
                 timeout_s: float = 30.0, busy_timeout_s: float = 10.0,
                 keep_on_camera: bool = False) -> None:
        super().__init__(name)
        if not (port == "auto" or _GP_PORT.match(port) or _VIDPID.match(port)):
            raise ValueError(f"gphoto2 camera port must be 'auto', 'usb:VID:PID' or a libgphoto2 "
                             f"port like 'usb:001,005', got {port!r}")
        self.port, self.model = port, model
        self.timeout_s, self.busy_timeout_s = timeout_s, busy_timeout_s
        self.keep_on_camera = keep_on_camera
        self._gp: Any = None
        self._camera: Any = None
        self._values: dict[str, float | None] = {}

    @classmethod
    def from_config(cls, name: str, section: dict[str, Any], **context: Any) -> "Gphoto2Camera":
        """Build from a rig-file section: ``port`` plus optional ``model``, ``timeout_s``,
        ``busy_timeout_s``, ``keep_on_camera``."""
        from .rig import driver_options
        allowed = {"model", "timeout_s", "busy_timeout_s", "keep_on_camera"}
        return cls(name, section["port"], **driver_options(name, section, "gphoto2", allowed))

    # -- errors -------------------------------------------------------------------------------
    def _error(self, exc: Exception, what: str) -> RigError:
        gp, code = self._gp, getattr(exc, "code", None)
        text = f"{what}: {exc}"
        if code == gp.GP_ERROR_CAMERA_BUSY:
            return DeviceBusy(text, device=self.name)
        if code == gp.GP_ERROR_TIMEOUT:
            return DeviceTimeout(text, device=self.name)
        if code in (gp.GP_ERROR_IO_USB_FIND, gp.GP_ERROR_MODEL_NOT_FOUND, gp.GP_ERROR_IO):
            return Disconnected(text, device=self.name)
        if code == gp.GP_ERROR_IO_USB_CLAIM:
            return Disconnected(f"{text} (another program holds the camera, e.g. "
                                "gvfs-gphoto2-volume-monitor)", device=self.name)
        if code == gp.GP_ERROR_CORRUPTED_DATA:
            return ProtocolError(text, device=self.name)
        return DeviceError(code, text, device=self.name)

    def _call(self, what: str, fn, *args):
        """Call libgphoto2, retrying "camera busy" with back-off, mapping errors to typed ones."""
        deadline, delay = time.monotonic() + self.busy_timeout_s, 0.05
        while True:
            try:
                return fn(*args)
            except self._gp.GPhoto2Error as exc:
                if exc.code != self._gp.GP_ERROR_CAMERA_BUSY or time.monotonic() + delay > deadline:
                    raise self._error(exc, what) from None
            time.sleep(delay)
            delay = min(2 * delay, 0.5)

    # -- link ---------------------------------------------------------------------------------
    def _gp_port(self) -> str | None:
        m = _VIDPID.match(self.port)
        if m is None:
            return None if self.port == "auto" else self.port
        import usb.core
        from .ptp_camera import libusb_backend
        try:
            dev = usb.core.find(idVendor=int(m.group(1), 16), idProduct=int(m.group(2), 16),
                                backend=libusb_backend())
        except usb.core.USBError as exc:
            raise Disconnected(f"USB enumeration for {self.port} failed: {exc}", device=self.name) from None
        if dev is None:
            raise Disconnected(f"no USB device {self.port} found", device=self.name)
        return f"usb:{dev.bus:03d},{dev.address:03d}"

    def connect(self) -> None:
        """Select the port (and model), initialise the camera, read its settings."""
        self.close()
        gp = self._gp = _gphoto2()
        camera = gp.Camera()
        port = self._gp_port()
        if port is not None:
            ports = gp.PortInfoList()
            self._call("port list", ports.load)
            camera.set_port_info(ports[self._call("port lookup", ports.lookup_path, port)])
        if self.model:
            abilities = gp.CameraAbilitiesList()
            self._call("camera list", abilities.load)
            camera.set_abilities(abilities[self._call("model lookup", abilities.lookup_model,
                                                      self.model)])
        self._call("camera init", camera.init)
        self._camera = camera
        self._refresh()

    def close(self) -> None:
        if self._camera is not None:
            try:
                self._camera.exit()
            except self._gp.GPhoto2Error:
                pass
            self._camera = None

    @property
    def connected(self) -> bool:
        return self._camera is not None

    def _cam(self) -> Any:
        if self._camera is None:
            raise Disconnected("not connected; call connect() first", device=self.name)
        return self._camera

    # -- settings -----------------------------------------------------------------------------
    def _widget(self, config: Any, setting: str) -> Any:
        for wname in _WIDGETS[setting]:
            try:
                return config.get_child_by_name(wname)
            except self._gp.GPhoto2Error:
                continue
        return None

    def _refresh(self) -> None:
        config = self._call("read config", self._cam().get_config)
        for setting in _WIDGETS:
            widget = self._widget(config, setting)
            self._values[setting] = None if widget is None else parse_choice(str(widget.get_value()))

    def _set(self, setting: str, value: float, unit: str) -> float:
        if not (math.isfinite(value) and value > 0):
            raise ValueError(f"{setting} must be a positive finite number, got {value!r}")
        camera = self._cam()
        config = self._call("read config", camera.get_config)
        widget = self._widget(config, setting)
        if widget is None:
            raise DeviceError("unsupported", f"the camera offers no {setting} setting",
                              device=self.name)
        choices = {c: v for c in widget.get_choices() if (v := parse_choice(str(c))) and v > 0}
        if not choices:
            raise DeviceError("unsupported", f"no numeric {setting} choices (mode dial?)",
                              device=self.name)
        lo, hi = min(choices.values()), max(choices.values())
        if not lo / _RANGE_SLACK <= value <= hi * _RANGE_SLACK:
            raise LimitError(value, (lo, hi), unit, device=self.name, what=setting)
        best = min(choices, key=lambda c: abs(math.log(choices[c] / value)))
        widget.set_value(best)
        self._call(f"set {setting}", camera.set_config, config)
        self._refresh()
        return self._values[setting] or choices[best]

    @property
    def exposure_s(self) -> float:
        value = self._values.get("exposure")
        if value is None:
            raise DeviceError("unsupported", "the camera does not report a numeric shutter speed",
                              device=self.name)
        return value

    def set_exposure(self, seconds: float) -> float:
        """Nearest offered shutter speed to ``seconds``; returns what the camera reports, s."""
        return self._set("exposure", float(seconds), "s")

    @property
    def iso(self) -> float | None:
        return self._values.get("iso")

    def set_iso(self, iso: float) -> float:
        """Nearest offered ISO; returns what the camera reports."""
        return self._set("iso", float(iso), "ISO")

    @property
    def fnumber(self) -> float | None:
        return self._values.get("fnumber")

    def set_fnumber(self, fnumber: float) -> float:
        """Nearest offered f-number; returns what the camera reports."""
        return self._set("fnumber", float(fnumber), "f/")

    # -- capture ------------------------------------------------------------------------------
    def capture(self) -> Frame:
        """Capture, download the file, delete it from the card (unless ``keep_on_camera``)."""
        gp, camera = self._gp, self._cam()
        exposure, iso, fnumber = self.exposure_s, self.iso, self.fnumber  # no numeric shutter: raise
        path = self._call("capture", camera.capture, gp.GP_CAPTURE_IMAGE)
        stamp = time.time()
        cfile = self._call("download", camera.file_get, path.folder, path.name,
                           gp.GP_FILE_TYPE_NORMAL)
        data = bytes(memoryview(cfile.get_data_and_size()))
        if not self.keep_on_camera:
            self._call("delete", camera.file_delete, path.folder, path.name)
        return Frame(data=data, filename=path.name, exposure_s=exposure, iso=iso,
                     fnumber=fnumber, timestamp=stamp,
                     metadata={"folder": path.folder, "size": len(data)})

    def read(self) -> dict[str, dict[str, Any]]:
        self._refresh()
        return {"exposure_s": reading(self._values.get("exposure"), "s"),
                "iso": reading(self.iso, "ISO"), "fnumber": reading(self.fnumber, "f/")}

    def describe(self) -> dict[str, Any]:
        out: dict[str, Any] = {"driver": "gphoto2", "port": self.port, "model": self.model}
        if self._camera is not None:
            summary = self._call("summary", self._camera.get_summary)
            out["summary"] = str(summary.text if hasattr(summary, "text") else summary)
        return out
