"""PtpCameraSim against a generic PTP client written by others: ``ptpy`` (PyPI, a ``test`` extra),
over the simulator's pyusb backend, running the sequence libgphoto2 and ptpy run after
connecting: GetDeviceInfo -> OpenSession -> GetStorageIDs -> GetStorageInfo -> GetNumObjects ->
GetObjectHandles -> GetObjectInfo -> GetThumb -> GetPartialObject -> GetObject -> CloseSession.

ptpy decodes every dataset with its own parsers (``construct`` structures), so the simulator's
StorageInfo, ObjectInfo and DeviceInfo bytes are checked by software written elsewhere; the
operation codes it names are checked against ptpy's table and against libgphoto2's ``ptp.h``
(``PTP_OC_GetStorageInfo 0x1005`` ... ``PTP_OC_GetPartialObject 0x101B``).

ptpy 0.3.2 pins construct 2.8.8, which still calls ``collections.Sequence`` (moved to
``collections.abc`` and removed from ``collections`` in Python 3.10); the fixture below restores
that alias for the duration of these tests and nothing else is patched.
"""
from __future__ import annotations

import collections
import collections.abc
import io
import time

import cv2
import numpy as np
import pytest
import tifffile
import usb.core

from sims.ptp_sim import OP, STORAGE_ID, PtpCameraSim

pytest.importorskip("construct", reason="ptpy (test extra) not installed")

# libgphoto2 camlibs/ptp2/ptp.h
LIBGPHOTO2_OC = {"GetDeviceInfo": 0x1001, "OpenSession": 0x1002, "CloseSession": 0x1003,
                 "GetStorageIDs": 0x1004, "GetStorageInfo": 0x1005, "GetNumObjects": 0x1006,
                 "GetObjectHandles": 0x1007, "GetObjectInfo": 0x1008, "GetObject": 0x1009,
                 "GetThumb": 0x100A, "DeleteObject": 0x100B, "InitiateCapture": 0x100E,
                 "GetDevicePropDesc": 0x1014, "GetDevicePropValue": 0x1015,
                 "SetDevicePropValue": 0x1016, "GetPartialObject": 0x101B}


@pytest.fixture(scope="module")
def ptpy():
    added = not hasattr(collections, "Sequence")
    if added:
        collections.Sequence = collections.abc.Sequence
    try:
        yield pytest.importorskip("ptpy", reason="ptpy (test extra) not installed")
    finally:
        if added:
            del collections.Sequence


@pytest.fixture
def camera(ptpy):
    sim = PtpCameraSim()
    dev = usb.core.find(idVendor=sim.vendor_id, idProduct=sim.product_id, backend=sim)
    # ptpy's event thread reads the interrupt endpoint with pyusb's default timeout; a short one
    # lets it stop soon at teardown (the simulator answers bulk transfers at once)
    dev.default_timeout = 200
    cam = ptpy.PTPy(device=dev, raw=True)
    try:
        yield sim, cam
    finally:
        cam._shutdown()


def test_codes_agree_with_libgphoto2():
    assert OP == LIBGPHOTO2_OC


def test_generic_client_sequence(camera):
    sim, cam = camera
    info = cam.get_device_info()
    assert (info.Manufacturer, info.Model, info.SerialNumber) == ("gonio", "SimCam PTP", "SIM0001")
    # ptpy turns the advertised codes into its own names: every operation it will call is there
    assert set(LIBGPHOTO2_OC) <= set(info.OperationsSupported)
    with cam.session():
        assert cam.initiate_capture().ResponseCode == "OK"
        deadline = time.monotonic() + 2
        while not sim.objects and time.monotonic() < deadline:
            time.sleep(0.01)
        (handle, obj), = sim.objects.items()
        data = obj["data"]
        assert list(cam.get_storage_ids()) == [STORAGE_ID]
        storage = cam.get_storage_info(STORAGE_ID)
        assert (storage.StorageType, storage.FilesystemType, storage.AccessCapability) == \
            ("RemovableRAM", "DCF", "ReadWrite")
        assert storage.MaxCapacity == sim.card_bytes
        assert storage.FreeSpaceInBytes == sim.card_bytes - len(data)
        assert storage.FreeSpaceInImages == sim.store_capacity - 1
        assert cam.get_num_objects(0xFFFFFFFF) == 1
        assert list(cam.get_object_handles(0xFFFFFFFF)) == [handle]
        assert list(cam.get_object_handles(STORAGE_ID, all_formats=True, in_root=True)) == [handle]
        oi = cam.get_object_info(handle)
        assert (oi.ObjectFormat, oi.ObjectCompressedSize, oi.Filename) == ("DNG", len(data), "IMG_0001.DNG")
        assert (oi.ImagePixWidth, oi.ImagePixHeight) == (600, 400)
        thumb = cam.get_thumb(handle)
        assert thumb.ResponseCode == "OK" and oi.ThumbFormat == "EXIF_JPEG"
        assert len(thumb.Data) == oi.ThumbCompressedSize
        # OpenCV's decoder reads the thumbnail at the size ObjectInfo announced, and it shows the
        # placeholder scene (brighter to the right, as the raw mosaic is)
        image = cv2.imdecode(np.frombuffer(thumb.Data, np.uint8), cv2.IMREAD_GRAYSCALE)
        assert image.shape == (oi.ThumbPixHeight, oi.ThumbPixWidth)
        raw = tifffile.imread(io.BytesIO(data))
        assert image[:, -20:].mean() > image[:, :20].mean() + 40
        assert np.corrcoef(image.ravel(), raw[::4, ::4].ravel())[0, 1] > 0.95
        part = cam.get_partial_object(handle, 100, 1000)
        assert part.ResponseCode == "OK" and list(part.Parameter) == [1000]
        assert bytes(part.Data) == data[100:1100]
        tail = cam.get_partial_object(handle, len(data) - 10, 0, until_end=True)
        assert list(tail.Parameter) == [10] and bytes(tail.Data) == data[-10:]
        whole = cam.get_object(handle)
        assert bytes(whole.Data) == data
    assert [op for op, _ in sim.commands] == [
        0x1001, 0x1002, 0x100E, 0x1004, 0x1005, 0x1006, 0x1007, 0x1007, 0x1008, 0x100A,
        0x101B, 0x101B, 0x1009, 0x1003]
