"""Stored pixel values -> radiance, as SCAN_BUNDLE.md defines it ("What a pixel measures").

lin(v) = (v / (2^bit_depth − 1))^gamma for integer images; float32 TIFF values are linear
already. L = (lin(v) − lin(v_dark)) / exposure.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np

from worker.bundle.matching import numbers_equal


def linearize(
    values: np.ndarray, *, bit_depth: int, gamma: float, out: np.ndarray | None = None
) -> np.ndarray:
    """lin(v): stored values (H, W) uint8/uint16 or float32 -> linear radiance (H, W) float32.

    Integer values are scaled by 1 / (2^bit_depth − 1) and raised to ``gamma``; float32
    values are returned as a float32 copy (bit depth and gamma do not apply). The input is
    never modified.  ``out``: (H, W) float32 array to write lin(v) into (same values).
    """
    if out is not None and (out.shape != values.shape or out.dtype != np.float32):
        raise ValueError(f"out: must be float32 of shape {values.shape}")
    if values.dtype == np.float32:
        if out is None:
            return values.copy()
        np.copyto(out, values)
        return out
    if values.dtype not in (np.uint8, np.uint16):
        raise ValueError(f"values: dtype must be uint8, uint16 or float32, not {values.dtype}")
    if not 8 <= bit_depth <= 16:
        raise ValueError(f"bit_depth: must be in 8..16, not {bit_depth}")
    if not gamma > 0:
        raise ValueError(f"gamma: must be > 0, not {gamma}")
    full_scale = float(2**bit_depth - 1)
    if gamma == 1.0:
        # The values are cast to float32 exactly, then scaled: astype and *= in one pass.
        return np.multiply(values, np.float32(1.0 / full_scale), out=out, dtype=np.float32)
    # A lookup table makes any gamma cost one gather instead of a pow per pixel.
    levels = np.arange(np.iinfo(values.dtype).max + 1, dtype=np.float64)
    lut = np.power(levels / full_scale, gamma).astype(np.float32)
    # mode='clip' changes nothing (the table covers the dtype's range) but lets np.take
    # write into ``out`` without its buffered copy.
    return np.take(lut, values, out=out, mode="clip")


def select_dark(exposure: float, darks: Sequence[tuple[int, float]]) -> int | None:
    """Index of the dark frame that corrects a frame of relative ``exposure``.

    ``darks`` holds ``(frame index, exposure)`` pairs. The spec's rule: the dark of the same
    exposure (within 1e-6; the first in manifest order), else the one whose exposure is
    nearest in ratio, |log(e_dark / e)| smallest, the shorter exposure on a tie; none: None.
    """
    if not exposure > 0:
        raise ValueError(f"exposure: must be > 0, not {exposure}")
    same = [index for index, e in darks if numbers_equal(e, exposure)]
    if same:
        return min(same)
    best: tuple[float, float, int] | None = None
    for index, e in darks:
        distance = abs(math.log(e / exposure))
        # Ratios like 1/3 and 3 give logs equal up to rounding: treat as a tie.
        candidate = (round(distance, 12), e, index)
        if best is None or candidate < best:
            best = candidate
    return None if best is None else best[2]


def radiance(
    values: np.ndarray,
    dark_linear: np.ndarray | None,
    *,
    bit_depth: int,
    gamma: float,
    exposure: float,
    out: np.ndarray | None = None,
) -> np.ndarray:
    """L = (lin(v) − lin(v_dark)) / exposure, (H, W) float32.

    ``dark_linear`` is lin(v_dark) (H, W) float32 from `linearize`, or None for no dark (0).
    ``out``: (H, W) float32 array to write L into, e.g. a slice of the caller's stack (no
    fresh frame and no copy per image).
    """
    if not exposure > 0:
        raise ValueError(f"exposure: must be > 0, not {exposure}")
    out = linearize(values, bit_depth=bit_depth, gamma=gamma, out=out)
    if dark_linear is not None:
        if dark_linear.shape != out.shape:
            raise ValueError(f"dark_linear: shape {dark_linear.shape} != values {out.shape}")
        out -= dark_linear
    if exposure != 1.0:
        out /= np.float32(exposure)
    return out
