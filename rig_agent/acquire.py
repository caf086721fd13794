"""Drive the rig through a scan's shots, spooling every frame before the next move.

:func:`capture` is the same for a new scan and for ``rig-agent resume``: it adopts
frames a crash left unjournaled, homes the stage if it lost its position, and
captures only what the journal does not hold. A device failure stops the loop with
the spool consistent and the reason recorded in ``state.json``.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from rig_agent.devices.base import Camera, DeviceError, capture_average
from rig_agent.devices.factory import Devices
from rig_agent.spool import SpoolScan

Progress = Callable[[int, int], None]


class ScanInterrupted(RuntimeError):
    """Capture stopped on a device problem; the message says what and how to continue."""


def capture(
    scan: SpoolScan,
    devices: Devices,
    *,
    elevation_mm: float,
    averaging: int = 1,
    progress: Progress | None = None,
) -> None:
    """Capture every pending shot of ``scan``; raises :class:`ScanInterrupted` on failure."""
    scan.recover()
    shots = scan.shots
    pending = scan.pending()
    total, done = len(shots), len(shots) - len(pending)
    if progress:
        progress(done, total)
    scan.update_state(phase="capturing", problem=None)
    current = None
    try:
        if devices.stage.needs_homing():
            devices.stage.home()
        for shot in pending:
            if shot.kind != "dark":
                target = (round(shot.azimuth_deg % 360.0, 3), elevation_mm)
                if target != current:
                    devices.stage.move_to(azimuth_deg=target[0], elevation_mm=elevation_mm)
                    current = target
            devices.projector.show(shot.pattern, azimuth_deg=shot.azimuth_deg or 0.0)
            devices.camera.set_exposure(shot.exposure)
            image = capture_average(devices.camera, count=averaging)
            _check_frame(image, devices.camera, shot.file)
            scan.save_frame(shot, image)
            done += 1
            if progress:
                progress(done, total)
    except DeviceError as exc:
        state = scan.update_state(phase="interrupted", problem=str(exc))
        raise ScanInterrupted(
            f"scan {scan.id} stopped after {done} of {total} frames: {state['problem']}. "
            f"Every frame captured so far is safe in {scan.path}. When the problem is fixed, "
            f"run `rig-agent resume {scan.id[:8]}`."
        ) from exc
    except BaseException as exc:  # Ctrl-C or a bug: record it, keep every frame, re-raise
        scan.update_state(phase="interrupted", problem=f"the agent stopped ({exc!r})")
        raise
    scan.update_state(phase="captured", problem=None)


def _check_frame(image: np.ndarray, camera: Camera, name: str) -> None:
    if image.shape != (camera.height, camera.width):
        raise DeviceError(
            f"frame {name}: the camera delivered {image.shape} instead of "
            f"({camera.height}, {camera.width})"
        )
    if image.dtype not in (np.uint8, np.uint16):
        raise DeviceError(f"frame {name}: the camera delivered {image.dtype}, not uint8/uint16")
