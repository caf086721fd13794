"""Cameras: an OpenCV (V4L2/UVC) backend; vendor SDKs implement :class:`~rig_agent.devices.base.Camera`.

A vendor SDK driver (GenICam, Basler pylon, FLIR Spinnaker, …) needs only the four
members of the ``Camera`` interface: ``width``, ``height``, ``bit_depth``,
``set_exposure(relative)``, ``capture() -> (H, W) uint8/uint16`` and ``close()``.
Frames must be raw sensor values (no auto exposure, no gain, no gamma), stored
unshifted (a 12-bit sensor gives 0 … 4095 in a uint16).
"""

from __future__ import annotations

import numpy as np

from rig_agent.devices.base import Camera, DeviceError


class OpenCVCamera(Camera):
    """A UVC camera through ``cv2.VideoCapture`` (V4L2 on Linux), 8-bit monochrome.

    ``device`` is an index (``0``) or a path (``/dev/video0``); ``base_exposure`` is the
    driver's ``CAP_PROP_EXPOSURE`` value for relative exposure 1.0 (for V4L2 in units of
    100 µs); relative exposures scale it linearly.
    """

    def __init__(
        self,
        device: int | str,
        *,
        width: int,
        height: int,
        base_exposure: float = 100.0,
    ) -> None:
        import cv2  # optional at import time: only this backend needs OpenCV

        self._cv2 = cv2
        self.width, self.height, self.bit_depth = width, height, 8
        self.base_exposure = base_exposure
        self._capture = cv2.VideoCapture(device, cv2.CAP_V4L2)
        if not self._capture.isOpened():
            self._capture.release()
            self._capture = None
            raise DeviceError(
                f"no camera found at {device!r}: check that it is plugged in, that no other "
                "program uses it, and the `camera_device` setting (`v4l2-ctl --list-devices` "
                "lists the cameras)"
            )
        self._capture.set(cv2.CAP_PROP_FRAME_WIDTH, width)
        self._capture.set(cv2.CAP_PROP_FRAME_HEIGHT, height)
        self._capture.set(cv2.CAP_PROP_AUTO_EXPOSURE, 1)  # V4L2: 1 = manual exposure
        self.set_exposure(1.0)

    def set_exposure(self, exposure: float) -> None:
        if not exposure > 0:
            raise ValueError(f"exposure must be > 0, got {exposure!r}")
        self._capture.set(self._cv2.CAP_PROP_EXPOSURE, self.base_exposure * exposure)

    def capture(self) -> np.ndarray:
        ok, frame = self._capture.read()
        if not ok or frame is None:
            raise DeviceError("the camera returned no image; check its USB cable and power")
        if frame.ndim == 3:
            frame = self._cv2.cvtColor(frame, self._cv2.COLOR_BGR2GRAY)
        if frame.shape != (self.height, self.width):
            raise DeviceError(
                f"the camera delivers {frame.shape[1]}×{frame.shape[0]} images, not the "
                f"configured {self.width}×{self.height}; fix `camera_width`/`camera_height`"
            )
        return frame.astype(np.uint8, copy=False)

    def close(self) -> None:
        capture, self._capture = getattr(self, "_capture", None), None
        if capture is not None:
            capture.release()
