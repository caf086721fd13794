"""Frame plumbing shared by the measurement stages: angle keys, threaded prefetch, BLAS threads."""

from __future__ import annotations

from collections.abc import Iterator, Sequence
from concurrent.futures import ThreadPoolExecutor

import numpy as np
from threadpoolctl import threadpool_limits

__all__ = ["angle_key", "prefetch", "single_threaded_blas"]


def prefetch(
    bundle, groups: Sequence[Sequence], workers: int = 2, ahead: int = 2, reuse: bool = False
) -> Iterator[np.ndarray]:
    """Radiance stacks of the groups, in order, decoded by `workers` threads frame by frame
    up to `ahead` groups beyond the one the caller works on.

    Frames, not groups, are the unit of work: the threads never wait for the caller to take
    a group before starting on the next (a group-at-a-time pipeline left a core idle
    whenever one group took longer to process than the next one to decode).
    reuse: a stack is only valid until the next one is requested, whose buffer it may then
    become (a fresh 40 MB buffer per group costs its page faults: 0.17 CPU s over the 40
    fringe groups of a 1.3 Mpx scan).
    """
    if not groups:
        return
    cam = bundle.manifest.camera
    queue = [(g, i, f) for g, group in enumerate(groups) for i, f in enumerate(group)]
    stacks: dict[int, np.ndarray] = {}
    futures: dict[int, list] = {}
    spare: list[np.ndarray] = []

    def fill(stack: np.ndarray, i: int, frame) -> None:
        bundle.radiance(frame, out=stack[i])  # no fresh frame and copy per image

    with ThreadPoolExecutor(max_workers=workers) as pool:
        nxt = 0
        for g in range(len(groups)):
            while nxt < len(queue) and queue[nxt][0] <= g + ahead:
                gg, i, frame = queue[nxt]
                if gg not in stacks:
                    shape = (len(groups[gg]), cam.height, cam.width)
                    match = next((k for k, a in enumerate(spare) if a.shape == shape), None)
                    stacks[gg] = (
                        spare.pop(match) if match is not None else np.empty(shape, np.float32)
                    )
                futures.setdefault(gg, []).append(pool.submit(fill, stacks[gg], i, frame))
                nxt += 1
            for future in futures.pop(g):
                future.result()
            stack = stacks.pop(g)
            yield stack
            if reuse:  # the caller is done with it: it asked for the next one
                spare.append(stack)
            del stack


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
