"""Frame plumbing shared by the measurement stages: angle keys and threaded prefetch."""

from __future__ import annotations

from collections.abc import Iterator, Sequence
from concurrent.futures import ThreadPoolExecutor

import numpy as np

__all__ = ["angle_key", "prefetch"]


def prefetch(bundle, groups: Sequence[Sequence], workers: int = 2) -> Iterator[np.ndarray]:
    """Radiance stacks of the groups, decoding group i+1 while the caller works on group i."""
    if not groups:
        return
    with ThreadPoolExecutor(max_workers=1) as pool:
        future = pool.submit(bundle.radiance_many, groups[0], max_workers=workers)
        for i in range(len(groups)):
            stack = future.result()
            if i + 1 < len(groups):
                future = pool.submit(bundle.radiance_many, groups[i + 1], max_workers=workers)
            yield stack


def angle_key(angle: float) -> float:
    return round(float(angle) % 360.0, 6)
