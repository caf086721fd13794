"""Upload and asset-download throughput of the library service on loopback.

Starts the service with uvicorn in a subprocess (SQLite, local storage, an in-memory Celery
broker so no worker is needed), then

1. uploads a ~200 MB bundle ZIP in 8 MiB chunks (``PUT /uploads/{id}/chunks``), and
   completes it (SHA-256 + bundle validation + storing the ZIP);
2. downloads a 64 MiB ``model.glb`` asset whole, and in 8 MiB ``Range`` requests.

Prints a table (MB = 10^6 bytes). Usage: ``.venv/bin/python bench/upload_assets.py
[--bundle-mb 200] [--chunk-mib 8] [--repeat 3]``.
"""

from __future__ import annotations

import argparse
import hashlib
import os
import socket
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import httpx
import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

API = "/api/v1"


def free_port() -> int:
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return sock.getsockname()[1]


def make_bundle(out: Path, *, target_mb: float) -> Path:
    """A valid bundle ZIP of about ``target_mb`` MB: 16-bit noise frames (incompressible)."""
    from worker.bundle import write_bundle

    side = 2048
    frame_bytes = side * side * 2
    n = max(4, round(target_mb * 1e6 / frame_bytes))
    rng = np.random.default_rng(0)
    manifest = {
        "format": "cuneiform-scan",
        "version": 1,
        "scan": {"face": "obverse"},  # no scan.id: every run is a new scan, stored anew
        "camera": {"width": side, "height": side, "pixel_size_um": 20, "bit_depth": 16},
        "source": {"polar_deg": 45},
        "frames": [
            {"file": f"f{i:03d}.png", "kind": "photometric", "azimuth_deg": i * 360 / n}
            for i in range(n)
        ],
    }
    images = {
        f"f{i:03d}.png": rng.integers(0, 65535, (side, side), dtype=np.uint16) for i in range(n)
    }
    return write_bundle(out, manifest, images, as_zip=True)


def complete_parts(bundle: Path, store_dir: Path) -> list[tuple[str, float]]:
    """The steps of ``complete`` timed one by one, in this process."""
    from backend.storage import LocalStorage
    from backend.uploads import sha256_of
    from worker.bundle import validate_bundle

    t0 = time.perf_counter()
    digest = sha256_of(bundle)
    t1 = time.perf_counter()
    problems = validate_bundle(bundle)
    t2 = time.perf_counter()
    if problems:
        raise RuntimeError(f"the bench bundle is invalid: {problems[:3]}")
    LocalStorage(store_dir).put_file("bench/bundle.zip", bundle, sha256=digest)
    t3 = time.perf_counter()
    return [("sha256", t1 - t0), ("validate_bundle", t2 - t1), ("store (copy + sha256)", t3 - t2)]


def prepare(data_dir: Path, db_url: str) -> tuple[str, int]:
    """Migrate the DB; make an admin with a token and a tablet. Returns (token, tablet id)."""
    from backend import crud
    from backend.db import make_engine, make_sessionmaker, migrate, session_scope
    from backend.tables import Role

    migrate(db_url)
    engine = make_engine(db_url)
    with session_scope(make_sessionmaker(engine)) as session:
        user = crud.create_user(session, email="bench@example.org", role=Role.admin)
        _token, secret = crud.create_token(session, user=user, name="bench")
        tablet = crud.create_tablet(
            session, fields={"designation": "Bench", "is_public": True}, institution_id=None
        )
        tablet_id = tablet.id
    engine.dispose()
    return secret, tablet_id


def make_model(db_url: str, storage_dir: Path, scan_id: int, work: Path, glb_mib: int) -> int:
    """A stored model version with a ``glb_mib`` MiB model.glb, via backend.jobs."""
    from sqlalchemy import select

    from backend import jobs
    from backend.db import make_engine, make_sessionmaker
    from backend.storage import LocalStorage
    from backend.tables import Job

    model_dir = work / "model"
    model_dir.mkdir()
    (model_dir / "model.glb").write_bytes(os.urandom(glb_mib << 20))
    engine = make_engine(db_url)
    factory = make_sessionmaker(engine)
    with factory() as session:
        job_id = session.scalars(select(Job.id).where(Job.scan_id == scan_id)).first()
        if session.get(Job, job_id).state.value != "running":
            jobs.mark_running(session, job_id=job_id)
        model = jobs.mark_succeeded(
            session, job_id=job_id, model_dir=model_dir, storage=LocalStorage(storage_dir)
        )
        model_id = model.id
    engine.dispose()
    return model_id


def start_server(port: int, env: dict[str, str], http: str) -> subprocess.Popen:
    cmd = [
        sys.executable,
        "-m",
        "uvicorn",
        "--factory",
        "backend.main:create_app",
        "--host",
        "127.0.0.1",
        "--port",
        str(port),
        "--log-level",
        "warning",
        "--http",
        http,
    ]
    proc = subprocess.Popen(cmd, cwd=ROOT, env=env)
    deadline = time.monotonic() + 60
    while time.monotonic() < deadline:
        try:
            if httpx.get(f"http://127.0.0.1:{port}{API}/health", timeout=1).status_code == 200:
                return proc
        except httpx.TransportError:
            time.sleep(0.2)
    proc.kill()
    raise RuntimeError("the server did not start within 60 s")


def upload(
    client: httpx.Client, data: bytes, tablet_id: int, chunk: int
) -> tuple[float, float, dict]:
    created = client.post(
        f"{API}/uploads",
        json={"tablet_id": tablet_id, "filename": "bench.zip", "size_bytes": len(data)},
    )
    created.raise_for_status()
    upload_id = created.json()["id"]
    t0 = time.perf_counter()
    for offset in range(0, len(data), chunk):
        response = client.put(
            f"{API}/uploads/{upload_id}/chunks",
            params={"offset": offset},
            content=data[offset : offset + chunk],
            headers={"Content-Type": "application/octet-stream"},
        )
        response.raise_for_status()
    t1 = time.perf_counter()
    done = client.post(
        f"{API}/uploads/{upload_id}/complete", json={"sha256": hashlib.sha256(data).hexdigest()}
    )
    t2 = time.perf_counter()
    if done.status_code not in (200, 201):
        raise RuntimeError(f"complete failed: {done.status_code} {done.text[:300]}")
    return t1 - t0, t2 - t1, done.json()


def download(client: httpx.Client, url: str, size: int, chunk: int | None) -> float:
    t0 = time.perf_counter()
    if chunk is None:
        got = 0
        with client.stream("GET", url) as response:
            response.raise_for_status()
            for part in response.iter_bytes():
                got += len(part)
    else:
        got = 0
        for start in range(0, size, chunk):
            end = min(start + chunk, size) - 1
            response = client.get(url, headers={"Range": f"bytes={start}-{end}"})
            if response.status_code != 206:
                raise RuntimeError(f"range request answered {response.status_code}")
            got += len(response.content)
    elapsed = time.perf_counter() - t0
    if got != size:
        raise RuntimeError(f"downloaded {got} of {size} bytes")
    return elapsed


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--bundle-mb", type=float, default=200)
    parser.add_argument("--chunk-mib", type=int, default=8)
    parser.add_argument("--glb-mib", type=int, default=64)
    parser.add_argument("--repeat", type=int, default=3)
    parser.add_argument(
        "--http", default="auto", choices=["auto", "h11", "httptools"], help="uvicorn's parser"
    )
    parser.add_argument(
        "--bundle", type=Path, default=None, help="reuse this bundle ZIP instead of making one"
    )
    args = parser.parse_args()
    chunk = args.chunk_mib << 20

    with tempfile.TemporaryDirectory(prefix="bench-upload-") as tmp:
        work = Path(tmp)
        data_dir = work / "var"
        db_url = f"sqlite:///{data_dir / 'bench.db'}"
        token, tablet_id = prepare(data_dir, db_url)
        t0 = time.perf_counter()
        bundle = args.bundle or make_bundle(work / "bundle.zip", target_mb=args.bundle_mb)
        data = bundle.read_bytes()
        print(f"{len(data) / 1e6:.0f} MB bundle ready in {time.perf_counter() - t0:.1f} s")
        parts = complete_parts(bundle, work / "parts-store")
        port = free_port()
        env = dict(
            os.environ,
            HAMMURABI_ENVIRONMENT="test",
            HAMMURABI_DATA_DIR=str(data_dir),
            HAMMURABI_DATABASE_URL=db_url,
            HAMMURABI_SECRET_KEY="bench-" + "k" * 40,
            HAMMURABI_BROKER_URL="memory://",
            HAMMURABI_FRONTEND_DIST=str(work / "no-frontend"),
            HAMMURABI_UPLOAD_MAX_BYTES=str(10 * len(data)),
        )
        server = start_server(port, env, args.http)
        rows = []
        try:
            headers = {"Authorization": f"Bearer {token}"}
            base = f"http://127.0.0.1:{port}"
            with httpx.Client(base_url=base, headers=headers, timeout=600) as client:
                send_s, complete_s, scan_id = [], [], None
                for _ in range(args.repeat):
                    sent, completed, body = upload(client, data, tablet_id, chunk)
                    send_s.append(sent)
                    complete_s.append(completed)
                    scan_id = body["scan"]["id"]
                mb = len(data) / 1e6
                rows.append((f"upload {mb:.0f} MB in {args.chunk_mib} MiB chunks", min(send_s), mb))
                rows.append(("complete (sha256 + validate + store)", min(complete_s), mb))
                rows.extend((f"  of which {name}", seconds, mb) for name, seconds in parts)
                model_id = make_model(db_url, data_dir / "storage", scan_id, work, args.glb_mib)
                url = f"{API}/models/{model_id}/assets/model.glb"
                size = args.glb_mib << 20
                whole = min(download(client, url, size, None) for _ in range(args.repeat))
                ranged = min(download(client, url, size, chunk) for _ in range(args.repeat))
                rows.append((f"download {size / 1e6:.0f} MB asset, one GET", whole, size / 1e6))
                rows.append(
                    (
                        f"download {size / 1e6:.0f} MB asset, {args.chunk_mib} MiB Ranges",
                        ranged,
                        size / 1e6,
                    )
                )
        finally:
            server.terminate()
            server.wait(timeout=30)
    print(
        f"\nbest of {args.repeat} runs, loopback, uvicorn (1 process, --http {args.http}), "
        "SQLite, local storage\n"
    )
    print("| operation | time (s) | throughput (MB/s) |")
    print("|---|---:|---:|")
    for name, seconds, mb in rows:
        print(f"| {name} | {seconds:.2f} | {mb / seconds:.0f} |")


if __name__ == "__main__":
    main()
