"""What the measurement stages produce, and the error a bundle that cannot be reconstructed raises."""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field

import numpy as np

from worker.bundle import BundleError

__all__ = ["Measurements", "ReconstructionError", "bundle_errors_as_reconstruction_errors"]


class ReconstructionError(Exception):
    """The bundle cannot be reconstructed; the message names the culprit."""


@contextmanager
def bundle_errors_as_reconstruction_errors() -> Iterator[None]:
    """Inside: a bundle that cannot be read (BundleError, a missing path) raises
    ReconstructionError with the same message, so the CLI exits 2 naming it."""
    try:
        yield
    except BundleError as exc:
        raise ReconstructionError(str(exc)) from None
    except FileNotFoundError as exc:
        raise ReconstructionError(f"bundle: {exc}") from None


@dataclass
class Measurements:
    """Per-pixel products of stages 1–5, all (H, W[, 3]) float32 in the spec frame."""

    pixel_size_um: float
    shape: tuple[int, int]
    normals: np.ndarray | None = None
    albedo: np.ndarray | None = None  # grey ρ relative to white (photometric, else fringes)
    residual: np.ndarray | None = None
    lights_used: np.ndarray | None = None
    photometric_outliers: np.ndarray | None = None  # lit samples the fit left out
    # Pixels fitted from their neighbourhood's light set (photometric_fit.consensus_refit).
    photometric_consensus: np.ndarray | None = None
    # Per pixel, a high quantile of the photometric shading over the lights
    # (`recon.ground_mask.stack_peak`): the evidence of the dark-ground mask, computed for
    # bundles without fringe heights only.
    photometric_peak: np.ndarray | None = None
    photometric_polar_deg: float = 45.0
    rgb_linear: np.ndarray | None = None
    # rgb_linear as 8-bit sRGB, when the colour stage ran in the background (it encodes it
    # there, beside the fusion).
    rgb_srgb8: np.ndarray | None = None
    fringe_height_um: np.ndarray | None = None
    fringe_spread_um: np.ndarray | None = None
    fringe_sigma_um: np.ndarray | None = None  # predicted σ of fringe_height_um (phase noise)
    # Each azimuth's own heights and σ (A, H, W), NaN where it has none: their differences
    # measure the fringe noise's colour (`recon.band_wiener.fringe_noise_colour`).
    fringe_azimuth_heights_um: np.ndarray | None = None
    fringe_azimuth_sigma_um: np.ndarray | None = None
    azimuths_used: np.ndarray | None = None
    modulation: np.ndarray | None = None
    # Median B/A over the central half of the reference target, per (azimuth°, polar°, period
    # µm) of the first fringe azimuth: the projector's and camera's modulation transfer,
    # reported in report.json (not a camera blur: SCAN_BUNDLE.md).
    reference_modulation: dict = field(default_factory=dict)
    rough_height_um: np.ndarray | None = None  # smooth, filled: where the light came from
    cliff_samples: list = field(default_factory=list)  # per azimuth, recon.walls.CliffSamples
    used: dict = field(default_factory=dict)
    warnings: list[str] = field(default_factory=list)
    timings: dict = field(default_factory=dict)
    scan_info: dict = field(default_factory=dict)
    # Stages still running in the background (`measure_bundle(color_in_background=True)`).
    pending: list = field(default_factory=list)

    def finish(self) -> Measurements:
        """Wait for the stages still running in the background (re-raising their errors)."""
        while self.pending:
            self.pending.pop(0).result()
        return self
