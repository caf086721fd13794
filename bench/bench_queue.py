"""Workers: quick-preset reconstructions per hour with 1 and 2 worker processes, and the
queue's overhead per job (a no-op task), on the embedded broker (or --broker-url).

    .venv/bin/python bench/bench_queue.py [--jobs 4] [--noop-jobs 20] [--size 96x128]

Method: the scans are uploaded with no worker running (their jobs wait in the broker), then
K workers start; the clock runs from the moment every worker logged "ready" until the last
job row is ``succeeded``. No-op: ``worker.tasks.noop`` claims and finishes a job row without
work; its wall time per job is what the queue itself costs (broker round trip, claim,
heartbeat thread, job-row updates). Prints a Markdown table (docs/benchmarks.md, "Workers").
"""

from __future__ import annotations

import sys
from pathlib import Path

# Not named bench/queue.py: bench/ is first on sys.path when a bench script runs, and a
# queue.py there would replace the standard library's `queue` for every bench script.
sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

import argparse  # noqa: E402
import os  # noqa: E402
import shutil  # noqa: E402
import tempfile  # noqa: E402
import time  # noqa: E402

from backend.jobs import CeleryDispatcher  # noqa: E402
from worker.demo import LocalLibrary, bundle_zip_as_new_scan  # noqa: E402


def _wait_ready(library: LocalLibrary, n_workers: int, timeout_s: float = 300) -> None:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        ready = sum(" ready." in p.read_text() for p in library.logs.glob("worker-*.log"))
        if ready >= n_workers:
            return
        time.sleep(0.1)
    raise TimeoutError("workers did not start")


def _library(root: Path, name: str, env: dict[str, str]) -> tuple[LocalLibrary, int]:
    library = LocalLibrary(root / name, env=env)
    library.cli("migrate")
    library.create_admin_token()
    library.start_server()
    with library.client() as http:
        tablet = http.post("/tablets", json={"designation": f"bench {name}"})
    return library, tablet.raise_for_status().json()["id"]


def run_reconstructions(root: Path, zip_path: Path, n_workers: int, n_jobs: int, env) -> float:
    library, tablet_id = _library(root, f"w{n_workers}", env)
    try:
        job_ids = [
            library.upload_bundle_zip(
                bundle_zip_as_new_scan(zip_path, i, root), tablet_id=tablet_id
            )["job"]["id"]
            for i in range(n_jobs)
        ]
        for k in range(n_workers):
            library.start_worker(f"b{k}")
        _wait_ready(library, n_workers)
        t0 = time.perf_counter()
        rows = library.wait_jobs(job_ids, timeout_s=3600)
        elapsed = time.perf_counter() - t0
        if any(r["state"] != "succeeded" for r in rows):
            raise RuntimeError(f"some jobs failed: {rows}")
        return elapsed
    finally:
        library.stop()


def run_noops(root: Path, zip_path: Path, n_jobs: int, env) -> float:
    library, tablet_id = _library(root, "noop", env)
    try:
        # Real job rows (scans uploaded), sent as no-op tasks instead of reconstructions.
        result = library.upload_bundle_zip(zip_path, tablet_id=tablet_id)
        scan_id = result["scan"]["id"]
        import sqlite3

        with sqlite3.connect(library.data_dir / "hammurabi.db") as db:
            db.execute("DELETE FROM jobs")  # the upload's own reconstruction: not measured
            now = time.strftime("%Y-%m-%d %H:%M:%S.000000")
            ids = []
            for _ in range(n_jobs):
                cur = db.execute(
                    "INSERT INTO jobs (scan_id, tablet_id, kind, state, progress, timings, "
                    "attempts, enqueued_at, created_at) VALUES (?, ?, 'reconstruct', 'queued', "
                    "0, '{}', 0, ?, ?)",
                    (scan_id, tablet_id, now, now),
                )
                ids.append(cur.lastrowid)
        library.start_worker("noop")
        _wait_ready(library, 1)
        url = (
            env.get("HAMMURABI_BROKER_URL")
            or f"sqla+sqlite:///{library.data_dir / 'broker.sqlite'}"
        )
        dispatcher = CeleryDispatcher(broker_url=url, queue="reconstruct")
        t0 = time.perf_counter()
        for job_id in ids:
            dispatcher.send_task("worker.tasks.noop", args=[job_id], task_id=f"noop-{job_id}")
        rows = library.wait_jobs(ids, timeout_s=600)
        elapsed = time.perf_counter() - t0
        if any(r["state"] != "succeeded" for r in rows):
            raise RuntimeError(f"some no-op jobs failed: {rows}")
        return elapsed / n_jobs
    finally:
        library.stop()


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--jobs", type=int, default=4)
    parser.add_argument("--noop-jobs", type=int, default=20)
    parser.add_argument("--size", default="96x128", help="WIDTHxHEIGHT of the simulated scan")
    parser.add_argument("--broker-url", help="e.g. redis://127.0.0.1:6379/0 (default embedded)")
    args = parser.parse_args()
    width, height = (int(v) for v in args.size.split("x"))
    env = {"HAMMURABI_BROKER_URL": args.broker_url} if args.broker_url else {}
    root = Path(tempfile.mkdtemp(prefix="bench-queue-"))
    try:
        from worker.simulate import simulate_scan

        sim = simulate_scan(root / "sim", seed=11, preset="quick", size=(width, height))
        zip_path = Path(shutil.make_archive(str(root / "bundle"), "zip", sim.bundles["obverse"]))
        broker = "Redis" if args.broker_url else "embedded (SQLite)"
        print(f"broker: {broker}; scan: quick preset {width}×{height} px; cores: {os.cpu_count()}")
        print(f"load average at start: {os.getloadavg()[0]:.1f}\n")
        print("| workers | jobs | wall time (s) | jobs per hour |")
        print("|---|---|---|---|")
        for n_workers in (1, 2):
            elapsed = run_reconstructions(root, zip_path, n_workers, args.jobs, env)
            print(
                f"| {n_workers} | {args.jobs} | {elapsed:.1f} | {3600 * args.jobs / elapsed:.0f} |"
            )
        per_job = run_noops(root, zip_path, args.noop_jobs, env)
        print(
            f"\nqueue overhead (no-op job, 1 worker, {args.noop_jobs} jobs): {per_job:.2f} s per job"
        )
    finally:
        shutil.rmtree(root, ignore_errors=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
