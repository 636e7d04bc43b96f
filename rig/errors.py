"""Typed device errors.

Every error a driver raises is one of these: no raw pyserial / pyusb exception reaches the caller.
Each carries the device name and says what to do. ``retryable`` tells the capture runner whether
repeating the same request after a short back-off can succeed (busy, timeout) or whether an
operator must act (limits, homing, cable).
"""
from __future__ import annotations


class RigError(Exception):
    """Base of all device errors. ``device`` names the device (e.g. ``"turntable"``)."""

    retryable = False
    hint = ""

    def __init__(self, message: str, *, device: str = "") -> None:
        self.device = device
        self.message = message
        text = f"{device}: {message}" if device else message
        if self.hint:
            text = f"{text} ({self.hint})"
        super().__init__(text)


class DeviceTimeout(RigError):
    """The device did not answer (or did not finish) within the allowed time."""

    retryable = True
    hint = "check power and cable; the request may be retried"

    def __init__(self, message: str, *, device: str = "", timeout_s: float | None = None) -> None:
        self.timeout_s = timeout_s
        if timeout_s is not None:
            # to the millisecond: a deadline's remainder reads 1 s, not 0.999999 s
            message = f"{message} (no answer within {round(timeout_s, 3):g} s)"
        super().__init__(message, device=device)


class DeviceBusy(RigError):
    """The device refused the request because it is busy; retry after a short wait."""

    retryable = True
    hint = "the device is busy; retry shortly"


class DeviceError(RigError):
    """The device reported an error code. ``code`` is the device's own code, ``meaning`` its text."""

    def __init__(self, code: object, meaning: str, *, device: str = "") -> None:
        self.code = code
        self.meaning = meaning
        super().__init__(f"error {code}: {meaning}", device=device)


class LimitError(RigError):
    """A requested value lies outside the device's travel or settings range."""

    hint = "choose a value inside the limits"

    def __init__(self, value: float, limits: tuple[float, float], unit: str, *, device: str = "",
                 what: str = "target") -> None:
        self.value = value
        self.limits = limits
        self.unit = unit
        lo, hi = limits
        super().__init__(f"{what} {value:g} {unit} is outside the limits {lo:g}..{hi:g} {unit}",
                         device=device)


class NotHomed(RigError):
    """The axis has no reference position yet."""

    hint = "home the axis first (gonio rig home, or Axis.home())"


class Disconnected(RigError):
    """The device is not connected or the link was lost."""

    hint = "reconnect the cable / power and call connect() again"


class ProtocolError(RigError):
    """A reply could not be parsed (garbled, wrong checksum, unexpected frame). ``raw`` holds it."""

    retryable = True
    hint = "garbled reply; the request may be retried"

    def __init__(self, message: str, *, device: str = "", raw: bytes | None = None) -> None:
        self.raw = raw
        if raw is not None:
            message = f"{message}: {raw!r}"
        super().__init__(message, device=device)
