"""Device drivers over the real wire protocols and the device API (degrees, millimetres)."""
from .device import Axis, Camera, Device, Frame, LightPositioner, LightTarget, reading
from .errors import (DeviceBusy, DeviceError, DeviceTimeout, Disconnected, LimitError, NotHomed,
                     ProtocolError, RigError)
from .status import MoveStatus, wait_all

__all__ = ["Axis", "Camera", "Device", "Frame", "LightPositioner", "LightTarget", "reading", "DeviceBusy", "DeviceError",
           "DeviceTimeout", "Disconnected", "LimitError", "NotHomed", "ProtocolError", "RigError",
           "MoveStatus", "wait_all"]
from .rig import ConfigError, Rig, load_config  # noqa: E402

__all__ += ["ConfigError", "Rig", "load_config"]
