"""Frame plumbing shared by the measurement stages: angle keys, threaded prefetch, BLAS threads."""

from __future__ import annotations

from collections.abc import Iterator, Sequence
from concurrent.futures import ThreadPoolExecutor

import numpy as np
from threadpoolctl import threadpool_limits

__all__ = ["angle_key", "prefetch", "single_threaded_blas"]


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


def single_threaded_blas():
    """Context in which BLAS runs in the calling thread only.

    The measurement stages call BLAS on skinny products (K lights × pixels) that gain little
    from its threads, while the frames are decoded in other threads: OpenBLAS's idle threads
    spin between calls and took a core from the decoding (photometric stage: 4.8 CPU s with
    its threads, 2.9 without, same wall time).
    """
    return threadpool_limits(limits=1, user_api="blas")


def angle_key(angle: float) -> float:
    return round(float(angle) % 360.0, 6)
