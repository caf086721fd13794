"""Camera backends: the OpenCV one can only be checked for its error without a device."""

from __future__ import annotations

import numpy as np
import pytest

from rig_agent.devices.base import Camera, DeviceError, capture_average
from rig_agent.devices.camera import OpenCVCamera


def test_a_missing_uvc_camera_is_a_clear_error():
    with pytest.raises(DeviceError, match="no camera found at '/dev/video-rig-agent-none'"):
        OpenCVCamera("/dev/video-rig-agent-none", width=640, height=480)


class CountingCamera(Camera):
    width, height, bit_depth = 4, 3, 12

    def __init__(self, values):
        self.values = list(values)

    def set_exposure(self, exposure):
        pass

    def capture(self):
        return np.full((3, 4), self.values.pop(0), dtype=np.uint16)

    def close(self):
        pass


def test_averaging_n_frames_keeps_the_camera_encoding():
    mean = capture_average(CountingCamera([10, 11, 13, 14]), count=4)
    assert mean.dtype == np.uint16 and (mean == 12).all()
    assert (capture_average(CountingCamera([7]), count=1) == 7).all()
    with pytest.raises(ValueError, match="count"):
        capture_average(CountingCamera([1]), count=0)
