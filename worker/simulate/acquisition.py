"""The paper's standard acquisition as a list of frames, and the bundle manifest for it.

Dark frame(s); photometric frames at K azimuths; red/green/blue at a few azimuths; at a
few azimuths four phase steps (0, 90, 180, 270°) for each of the ten periods that double
from a quarter period across the projector field to 128 periods across it; the same
lit frames on the white reference target (SCAN_BUNDLE.md, "standard acquisition").
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from worker.simulate.noise import NoiseModel
from worker.simulate.rig import CHANNELS, FrameSpec

__all__ = [
    "FIELD_UM",
    "FRAME_MARGIN_UM",
    "PAPER_PIXEL_UM",
    "PRESETS",
    "Preset",
    "frame_file",
    "frame_size_for",
    "manifest",
    "periods_um",
    "plan_frames",
]

# The paper's camera: 1280×1024 pixels of 26.8 µm on the object plane.
PAPER_PIXEL_UM = 26.8
FIELD_UM = (1280 * PAPER_PIXEL_UM, 1024 * PAPER_PIXEL_UM)
# Support seen around a tablet when the frame follows the tablet (frame_size_for): enough
# for the mask and the reference statistics, little enough to cost few pixels.
FRAME_MARGIN_UM = 1500.0
PERIODS_ACROSS = tuple(0.25 * 2**k for k in range(10))  # 0.25 .. 128
PHASES_DEG = (0.0, 90.0, 180.0, 270.0)


@dataclass(frozen=True)
class Preset:
    """Image size, supersampling and the azimuths (degrees) of each kind of frame."""

    name: str
    width: int
    height: int
    supersample: int
    photometric_deg: tuple[float, ...]
    color_deg: tuple[float, ...]
    fringe_deg: tuple[float, ...]
    polar_deg: float = 45.0


PRESETS: dict[str, Preset] = {
    "quick": Preset(
        "quick",
        320,
        256,
        2,
        photometric_deg=tuple(np.arange(8) * 45.0),
        color_deg=(0.0, 90.0, 180.0, 270.0),
        fringe_deg=(0.0, 90.0, 180.0, 270.0),
    ),
    "paper": Preset(
        "paper",
        1280,
        1024,
        2,
        photometric_deg=tuple(np.arange(16) * 22.5),
        color_deg=(45.0, 135.0, 225.0, 315.0),
        fringe_deg=(0.0, 90.0, 180.0, 270.0),
    ),
}


def pixel_size_for(width: int, height: int) -> float:
    """Pixel size (µm) that keeps the paper's field of view (34.3 × 27.4 mm) in the frame."""
    return max(FIELD_UM[0] / width, FIELD_UM[1] / height)


def frame_size_for(
    extent_um: tuple[float, float], pixel_size_um: float, margin_um: float = FRAME_MARGIN_UM
) -> tuple[int, int]:
    """(width, height) px of a frame that holds an object ``extent_um`` (x, y) across plus
    ``margin_um`` of support on every side, at ``pixel_size_um``: the field follows the
    object, so a small tablet at the paper's 26.8 µm gives small frames. Even sizes."""
    if pixel_size_um <= 0:
        raise ValueError(f"pixel size must be > 0 µm, got {pixel_size_um}")
    out = []
    for extent in extent_um:
        n = int(np.ceil((float(extent) + 2 * margin_um) / pixel_size_um))
        out.append(max(16, n + n % 2))
    return out[0], out[1]


def periods_um(azimuth_deg: float, width: int, height: int, pixel_size_um: float) -> list[float]:
    """Fringe periods: the projector field's extent along u divided by 0.25, 0.5, … 128."""
    phi = np.radians(azimuth_deg)
    extent = abs(np.sin(phi)) * width * pixel_size_um + abs(np.cos(phi)) * height * pixel_size_um
    return [float(extent / n) for n in PERIODS_ACROSS]


def plan_frames(
    preset: Preset,
    *,
    width: int,
    height: int,
    pixel_size_um: float,
    noise: NoiseModel,
    rng: np.random.Generator,
) -> list[FrameSpec]:
    """All frames of one scan; exposures drawn from ``noise.exposures`` (darks for each one used).

    Fringe frames come grouped by (target, azimuth, period), the four phases in a row.
    """
    polar = preset.polar_deg

    def exposure(target: str) -> float:
        # An operator exposes the bright white target shorter and the dark clay longer.
        pool = [e for e in noise.exposures if (e <= 1.0 if target == "reference" else e >= 1.0)]
        pool = pool or list(noise.exposures)
        return float(rng.choice(pool)) if len(pool) > 1 else pool[0]

    lit: list[FrameSpec] = []
    for target in ("object", "reference"):
        for az in preset.photometric_deg:
            lit.append(
                FrameSpec("photometric", target, float(az), polar, exposure=exposure(target))
            )
        for az in preset.color_deg:
            for ch in CHANNELS:
                lit.append(
                    FrameSpec("color", target, float(az), polar, ch, exposure=exposure(target))
                )
        for az in preset.fringe_deg:
            for period in periods_um(az, width, height, pixel_size_um):
                e = exposure(target)  # one exposure per fringe set keeps the set consistent
                for ph in PHASES_DEG:
                    lit.append(FrameSpec("fringe", target, float(az), polar, None, period, ph, e))
    darks = [FrameSpec("dark", exposure=e) for e in sorted({f.exposure for f in lit})]
    return darks + lit


def frame_file(frame: FrameSpec, index: int) -> str:
    """Relative POSIX path of a frame's image in the bundle."""
    if frame.kind == "dark":
        return f"dark/dark_x{frame.exposure:.2f}.png"
    name = f"{frame.kind}_az{frame.azimuth_deg:05.1f}"
    if frame.kind == "color":
        name += f"_{frame.channel}"
    if frame.kind == "fringe":
        name += f"_p{frame.period_um:09.1f}_ph{frame.phase_deg:03.0f}"
    return f"{frame.target}/{index:04d}_{name}.png"


def manifest(
    frames: list[FrameSpec],
    files: list[str],
    *,
    face: str,
    pose: np.ndarray,
    seed: int,
    width: int,
    height: int,
    pixel_size_um: float,
    noise: NoiseModel,
    polar_deg: float,
    reflectance: float,
    psf_sigma_px: float | None = None,
    physics_name: str = "ideal",
) -> dict:
    """The manifest.json of the scan (SCAN_BUNDLE.md v1).

    ``psf_sigma_px``: the camera's calibrated PSF σ, written only when given. The scan id
    names a physics variant other than ``ideal`` (ideal ids are unchanged).
    """
    out = []
    for frame, file in zip(frames, files, strict=True):
        entry: dict = {"file": file, "kind": frame.kind}
        if frame.kind != "dark":
            entry["target"] = frame.target
            entry["azimuth_deg"] = frame.azimuth_deg
            if frame.polar_deg != polar_deg:
                entry["polar_deg"] = frame.polar_deg
        if frame.kind == "color":
            entry["channel"] = frame.channel
        if frame.kind == "fringe":
            entry["period_um"] = frame.period_um
            entry["phase_deg"] = frame.phase_deg
        if frame.exposure != 1.0:
            entry["exposure"] = frame.exposure
        out.append(entry)
    scan_id = f"sim-{seed}-{face}-{width}x{height}-{noise.name}"
    if physics_name != "ideal":
        scan_id += f"-{physics_name}"
    camera = {
        "width": width,
        "height": height,
        "pixel_size_um": pixel_size_um,
        "bit_depth": noise.bit_depth,
        "response_gamma": noise.response_gamma,
    }
    if psf_sigma_px is not None:
        camera["psf_sigma_px"] = psf_sigma_px
    return {
        "format": "cuneiform-scan",
        "version": 1,
        "scan": {
            "id": scan_id,
            "face": face,
            "pose": np.asarray(pose, float).tolist(),
            "tablet": {"designation": f"synthetic tablet {seed}", "simulator": "worker.simulate"},
        },
        "camera": camera,
        "source": {"polar_deg": polar_deg},
        "reference": {"reflectance": reflectance},
        "frames": out,
    }
