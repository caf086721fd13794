"""Small valid bundles to start from; tests break them one rule at a time.

Fixtures return plain functions so that each test builds fresh, independent data.
"""

from __future__ import annotations

import copy
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest

from worker.bundle import write_bundle

H, W = 12, 16
BIT_DEPTH = 12


def _valid() -> tuple[dict, dict[str, np.ndarray]]:
    """A 16×12 bundle: one dark, object + reference photometric (2 azimuths), colour (red),
    and one fringe set per target; distinct deterministic values per image."""
    rng = np.random.default_rng(7)
    frames: list[dict] = [{"file": "dark.png", "kind": "dark"}]
    for target in ("object", "reference"):
        for az in (0, 90):
            frames.append({"file": f"{target}/p{az}.png", "kind": "photometric", "azimuth_deg": az})
        frames.append(
            {"file": f"{target}/red.png", "kind": "color", "azimuth_deg": 45, "channel": "red"}
        )
        for phase in (0, 90, 180, 270):
            frames.append(
                {
                    "file": f"{target}/f{phase}.png",
                    "kind": "fringe",
                    "azimuth_deg": 30,
                    "period_um": 400,
                    "phase_deg": phase,
                }
            )
        for f in frames:
            if f["file"].startswith(target):
                f["target"] = target
    manifest = {
        "format": "cuneiform-scan",
        "version": 1,
        "scan": {"id": "scan-1", "face": "obverse", "tablet": {"designation": "P123456"}},
        "camera": {"width": W, "height": H, "pixel_size_um": 25.0, "bit_depth": BIT_DEPTH},
        "source": {"polar_deg": 40},
        "reference": {"reflectance": 0.95},
        "frames": frames,
    }
    images = {
        f["file"]: rng.integers(0, 2**BIT_DEPTH, size=(H, W), dtype=np.uint16) for f in frames
    }
    images["dark.png"] = rng.integers(0, 50, size=(H, W), dtype=np.uint16)
    return manifest, images


@pytest.fixture(scope="session")
def valid_bundle() -> Callable[[], tuple[dict, dict[str, np.ndarray]]]:
    """``valid_bundle()`` -> (manifest dict, images by path), fresh copies each call."""

    def make() -> tuple[dict, dict[str, np.ndarray]]:
        manifest, images = _valid()
        return copy.deepcopy(manifest), {k: v.copy() for k, v in images.items()}

    return make


@pytest.fixture
def written_bundle(tmp_path: Path, valid_bundle) -> Callable[..., Path]:
    """``written_bundle(name="b", as_zip=False, manifest=None, images=None)`` -> its path."""

    def write(name: str = "b", *, as_zip: bool = False, manifest=None, images=None) -> Path:
        m, i = valid_bundle()
        return write_bundle(
            tmp_path / name, manifest or m, images if images is not None else i, as_zip=as_zip
        )

    return write
