"""The registration's Poisson surface in a child process (``python -m worker.register.poisson
IN.npz OUT.npz``), so that the job's heartbeat thread keeps beating.

Open3D's screened Poisson reconstruction holds the GIL for its whole run (its pybind11 binding
does not release it): measured, 101 s without a single thread switch during a 320 × 256 px
registration on a loaded 2-core machine, so the job's heartbeat (worker/tasks.py, every few
seconds) stopped and the job looked stale after 15 s. A plain subprocess (not
multiprocessing: Celery's prefork workers are daemonic processes, which may not have
children) runs it while the worker's threads go on.
"""

from __future__ import annotations

import os
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np

__all__ = ["poisson_in_child"]

_PACKAGE_ROOT = Path(__file__).resolve().parents[2]  # the folder holding `worker/`


def poisson_in_child(
    pts: np.ndarray, nrm: np.ndarray, col: np.ndarray, depth: int, trim_quantile: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """`worker.register.merge.poisson_arrays` run by a child Python process; RuntimeError
    with the child's last words when it fails."""
    with tempfile.TemporaryDirectory(prefix="hammurabi-poisson-") as tmp:
        src, out = Path(tmp) / "in.npz", Path(tmp) / "out.npz"
        np.savez(src, pts=pts, nrm=nrm, col=col, depth=depth, trim_quantile=trim_quantile)
        # This very code in the child, whatever the working directory.
        env = {
            **os.environ,
            "PYTHONPATH": os.pathsep.join(
                p for p in (str(_PACKAGE_ROOT), os.environ.get("PYTHONPATH", "")) if p
            ),
        }
        proc = subprocess.run(
            [sys.executable, "-m", "worker.register.poisson", str(src), str(out)],
            env=env,
            capture_output=True,
            text=True,
            check=False,
        )
        if proc.returncode != 0:
            tail = (proc.stderr or proc.stdout or "").strip()[-1500:]
            raise RuntimeError(f"Poisson surface: the child process failed ({tail})")
        with np.load(out) as z:
            return z["vertices"], z["triangles"], z["normals"], z["colours"]


def main(argv: list[str]) -> int:
    from worker.register.merge import poisson_arrays

    src, out = argv
    with np.load(src) as z:
        args = (z["pts"], z["nrm"], z["col"], int(z["depth"]), float(z["trim_quantile"]))
    vertices, triangles, normals, colours = poisson_arrays(*args)
    with open(out, "wb") as fh:
        np.savez(fh, vertices=vertices, triangles=triangles, normals=normals, colours=colours)
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
