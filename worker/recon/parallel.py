"""Independent blocks of pixels shared out between threads.

numpy and OpenCV release the GIL on large arrays, so per-pixel work split into blocks
(rows, chunks of a flattened image, frames) runs on several cores from threads, without the
copies a process pool would need.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable
from concurrent.futures import ThreadPoolExecutor

__all__ = ["run_blocks"]


def run_blocks(work: Callable[[int], None], starts: Iterable[int], *, workers: int) -> None:
    """Call ``work(start)`` for every start: in up to ``workers`` threads when more than one
    block and worker, else in order in this thread. Exceptions propagate to the caller."""
    starts = list(starts)
    if workers > 1 and len(starts) > 1:
        with ThreadPoolExecutor(max_workers=min(workers, len(starts))) as pool:
            list(pool.map(work, starts))
    else:
        for start in starts:
            work(start)
