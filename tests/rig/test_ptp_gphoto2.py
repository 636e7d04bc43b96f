"""Gphoto2Camera (the vendor-operation seam) against a stand-in for the python-gphoto2 module."""
from __future__ import annotations

import sys
import types

import pytest

from rig.errors import DeviceBusy, DeviceError, Disconnected, LimitError
from rig.gphoto2_camera import Gphoto2Camera, parse_choice


class GPhoto2Error(Exception):
    def __init__(self, code):
        super().__init__(f"[{code}] libgphoto2 error")
        self.code = code


class Widget:
    def __init__(self, value, choices):
        self.value, self.choices = value, choices

    def get_value(self):
        return self.value

    def get_choices(self):
        return iter(self.choices)

    def set_value(self, v):
        assert v in self.choices
        self.value = v


class Config:
    def __init__(self, widgets):
        self.widgets = widgets

    def get_child_by_name(self, name):
        if name not in self.widgets:
            raise GPhoto2Error(-2)
        return self.widgets[name]


class FakeCamera:
    instances: list = []

    def __init__(self):
        self.widgets = {"shutterspeed": Widget("1/100", ["bulb", "1/4000", "1/250", "1/100", "1/60", "0.3", "30"]),
                        "iso": Widget("100", ["Auto", "100", "200", "400"]),
                        "aperture": Widget("8", ["5.6", "8", "11"])}
        self.files = {}
        self.busy = 0
        self.init_error = None
        FakeCamera.instances.append(self)

    def init(self):
        if self.init_error:
            raise GPhoto2Error(self.init_error)

    def exit(self):
        pass

    def get_config(self):
        return Config({k: Widget(w.value, w.choices) for k, w in self.widgets.items()})

    def set_config(self, config):
        if self.busy:
            self.busy -= 1
            raise GPhoto2Error(-110)
        self.widgets = config.widgets

    def capture(self, kind):
        name = f"IMG_{len(self.files) + 1:04d}.CR2"
        self.files[name] = f"raw@{self.widgets['shutterspeed'].value}".encode()
        return types.SimpleNamespace(folder="/store_00020001/DCIM/100CANON", name=name)

    def file_get(self, folder, name, kind):
        return types.SimpleNamespace(get_data_and_size=lambda: self.files[name])

    def file_delete(self, folder, name):
        del self.files[name]


@pytest.fixture
def fake_gp(monkeypatch):
    gp = types.ModuleType("gphoto2")
    gp.GPhoto2Error, gp.Camera = GPhoto2Error, FakeCamera
    gp.GP_CAPTURE_IMAGE, gp.GP_FILE_TYPE_NORMAL = 0, 1
    for name, code in dict(GP_ERROR_IO=-7, GP_ERROR_TIMEOUT=-10, GP_ERROR_IO_USB_FIND=-52,
                           GP_ERROR_IO_USB_CLAIM=-53, GP_ERROR_CORRUPTED_DATA=-102,
                           GP_ERROR_MODEL_NOT_FOUND=-105, GP_ERROR_CAMERA_BUSY=-110).items():
        setattr(gp, name, code)
    monkeypatch.setitem(sys.modules, "gphoto2", gp)
    FakeCamera.instances.clear()
    return gp


def test_missing_gphoto2_gives_install_hint(monkeypatch):
    monkeypatch.setitem(sys.modules, "gphoto2", None)  # import fails
    with pytest.raises(DeviceError, match=r"pip install 'gonio\[gphoto2\]'"):
        Gphoto2Camera("camera").connect()


def test_parse_choice():
    assert parse_choice("1/250") == 0.004 and parse_choice("0.3") == 0.3 and parse_choice("30") == 30
    assert parse_choice("f/5.6") == 5.6 and parse_choice("30s") == 30 and parse_choice('1"') == 1
    assert parse_choice("bulb") is None and parse_choice("Auto") is None and parse_choice("1/0") is None


def test_port_and_config_validation():
    with pytest.raises(ValueError, match="usb:VID:PID"):
        Gphoto2Camera("camera", "/dev/video0")
    cam = Gphoto2Camera.from_config("camera", {"driver": "gphoto2", "port": "usb:001,005",
                                               "keep_on_camera": True})
    assert cam.port == "usb:001,005" and cam.keep_on_camera
    with pytest.raises(ValueError, match=r"unknown key\(s\)"):
        Gphoto2Camera.from_config("camera", {"driver": "gphoto2", "port": "auto", "fps": 3})


def test_settings_snap_and_capture_deletes(fake_gp):
    cam = Gphoto2Camera("camera")
    cam.connect()
    assert (cam.exposure_s, cam.iso, cam.fnumber) == (0.01, 100.0, 8.0)
    assert cam.set_exposure(1 / 200) == 0.004 and cam.set_iso(350) == 400 and cam.set_fnumber(6) == 5.6
    with pytest.raises(LimitError):
        cam.set_exposure(120)
    frame = cam.capture()
    assert frame.data == b"raw@1/250" and frame.exposure_s == 0.004 and frame.filename == "IMG_0001.CR2"
    assert FakeCamera.instances[-1].files == {}
    frames = cam.bracket([1 / 60, 0.3])
    assert [f.exposure_s for f in frames] == [1 / 60, 0.3] and cam.exposure_s == 0.004


def test_busy_retried_then_bounded(fake_gp):
    cam = Gphoto2Camera("camera", busy_timeout_s=0.3)
    cam.connect()
    FakeCamera.instances[-1].busy = 2
    assert cam.set_iso(200) == 200
    FakeCamera.instances[-1].busy = 1000
    with pytest.raises(DeviceBusy):
        cam.set_iso(400)


def test_claimed_interface_is_disconnected_with_hint(fake_gp, monkeypatch):
    monkeypatch.setattr(FakeCamera, "init", lambda self: (_ for _ in ()).throw(GPhoto2Error(-53)))
    with pytest.raises(Disconnected, match="gvfs"):
        Gphoto2Camera("camera").connect()
