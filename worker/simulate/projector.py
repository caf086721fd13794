"""The projected fringe profile of a real projector: pixel grid, levels, response, defocus.

The projector displays, at each of its pixels j (pitch a on the object plane, centres
s_j along the fringe direction u), the value d_j = ½ + ½·m·cos(2π s_j/P + δ), quantised
to ``levels`` grey levels; its light output is d_j^γ (γ the projector's response); the
optics blur this staircase with a Gaussian of σ (defocus). On the reference plane the
pattern is thus

    F(s) = [G_σ * Σ_j rect((s - s_j)/a) · Q(d_j)^γ](s) / DC,

normalised by its mean DC so that F = 1 + m·cos(2π s/P + δ) for the ideal projector
(a → 0, no quantisation, γ = 1, σ = 0). A Gaussian defocus multiplies a sinusoid's
modulation by its MTF, exp(-2π²σ²/P²) (the Fourier transform of the Gaussian at 1/P),
so fine periods lose the most; the staircase and γ add harmonics.
"""

from __future__ import annotations

import numpy as np
from scipy.ndimage import gaussian_filter1d

__all__ = ["defocus_mtf", "fringe_profile"]

_MAX_GRID = 4_000_000  # samples of the 1-D profile, a guard against absurd ranges


def defocus_mtf(period_um: float, sigma_um: float) -> float:
    """Modulation transfer of a Gaussian blur of σ µm at period P µm: exp(-2π²σ²/P²)."""
    if period_um <= 0:
        raise ValueError(f"period_um must be > 0, got {period_um}")
    return float(np.exp(-2 * np.pi**2 * sigma_um**2 / period_um**2))


def fringe_profile(
    coord_um: np.ndarray,
    *,
    period_um: float,
    phase_rad: float,
    modulation: float,
    defocus_um: float = 0.0,
    pixel_um: float = 0.0,
    levels: int = 0,
    gamma: float = 1.0,
) -> np.ndarray:
    """Relative irradiance F (mean 1) of the pattern at reference-plane coordinates s = u·p'.

    coord_um: any shape, µm; returns float32 of the same shape. See the module docstring.
    """
    s = np.asarray(coord_um, dtype=np.float64)
    if period_um <= 0 or not 0 < modulation <= 1:
        raise ValueError("period_um must be > 0 and modulation in (0, 1]")
    mtf = defocus_mtf(period_um, defocus_um)
    if pixel_um == 0 and levels == 0 and gamma == 1:
        out = 1.0 + modulation * mtf * np.cos(2 * np.pi * s / period_um + phase_rad)
        return out.astype(np.float32)
    theta = np.linspace(0, 2 * np.pi, 4096, endpoint=False)
    dc = float(np.mean((0.5 + 0.5 * modulation * np.cos(theta)) ** gamma))

    def light(x: np.ndarray) -> np.ndarray:
        centres = (np.floor(x / pixel_um) + 0.5) * pixel_um if pixel_um > 0 else x
        shown = 0.5 + 0.5 * modulation * np.cos(2 * np.pi * centres / period_um + phase_rad)
        if levels:
            shown = np.rint(shown * (levels - 1)) / (levels - 1)
        return shown**gamma

    if defocus_um == 0:  # the staircase itself, exactly, at every sample
        return (light(s) / dc).astype(np.float32)
    # Defocus: blur the staircase on a fine 1-D grid (a quarter σ or finer), then interpolate.
    step = min(period_um / 64, defocus_um / 4, pixel_um / 8 if pixel_um > 0 else np.inf)
    pad = 4 * defocus_um + 2 * pixel_um + step
    lo, hi = float(s.min()) - pad, float(s.max()) + pad
    n = int(np.ceil((hi - lo) / step)) + 1
    if n > _MAX_GRID:
        step = (hi - lo) / (_MAX_GRID - 1)
        n = _MAX_GRID
    grid = lo + step * np.arange(n)
    blurred = gaussian_filter1d(light(grid), defocus_um / step, mode="nearest")
    return (np.interp(s, grid, blurred) / dc).astype(np.float32)
