"""The registration's Poisson surface leaves the GIL to the job's heartbeat thread
(worker/tasks.py `_Beat`): Open3D holds the GIL for the whole reconstruction, so it runs in a
child process (worker.register.poisson); a thread that wakes every 50 ms
keeps waking while it runs, as the heartbeat must (a stale heartbeat after 15 s made the
sweeper take a running registration for dead)."""

from __future__ import annotations

import threading
import time

import numpy as np

from worker.register.merge import merged_surface, poisson_arrays
from worker.register.pointcloud import ScanCloud


def _sphere_scan(n: int) -> ScanCloud:
    rng = np.random.default_rng(4)
    d = rng.normal(size=(n, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    return ScanCloud(10.0 * d, d, np.full_like(d, 0.5), 100.0, "s")


def _longest_pause_s(call) -> tuple[float, float, object]:
    """(longest gap between a 50 ms ticker's wake-ups, duration, result) during call()."""
    stop = threading.Event()
    gaps = [0.0]

    def tick() -> None:
        last = time.perf_counter()
        while not stop.wait(0.05):
            now = time.perf_counter()
            gaps.append(now - last)
            last = now

    ticker = threading.Thread(target=tick, daemon=True)
    ticker.start()
    t0 = time.perf_counter()
    try:
        result = call()
    finally:
        duration = time.perf_counter() - t0
        stop.set()
        ticker.join()
    return max(gaps), duration, result


def test_the_poisson_surface_leaves_the_gil_to_the_heartbeat():
    scan = _sphere_scan(20000)
    # In this process the reconstruction holds the GIL: the ticker stops for all of it.
    in_place, in_place_s, _ = _longest_pause_s(
        lambda: poisson_arrays(scan.points_mm, scan.normals, scan.colours, 7, 0.0)
    )
    assert in_place > 0.5 * in_place_s, (in_place, in_place_s)
    print(f"in place: {in_place:.2f} s pause of {in_place_s:.2f} s")
    # Through merged_surface it runs in a child process: the ticker keeps waking (a beat
    # every 50 ms; even a loaded machine wakes it well within a second).
    pause, duration, mesh = _longest_pause_s(lambda: merged_surface([scan], [np.eye(4)], depth=7))
    assert pause < max(1.0, 0.25 * in_place_s), (pause, duration, in_place_s)
    print(f"child process: {pause:.2f} s longest pause of {duration:.2f} s")
    r = np.linalg.norm(mesh.vertices, axis=1)
    assert np.sqrt(np.mean((r - 10.0) ** 2)) < 0.17 and len(mesh.faces) > 1000
