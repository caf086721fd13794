"""Concurrency benchmark (and the scenario of tests/backend/test_concurrency.py).

Starts the library service (``hammurabi serve``, one uvicorn process) on a free loopback
port in a subprocess, on a fresh SQLite file or a throwaway PostgreSQL database, seeded with
a staff user holding many never-used API tokens, a public tablet and a private tablet with
a model whose asset is a few MB. Then fires bursts of ``--concurrency`` simultaneous
requests of each kind (issue 16: the server used to deadlock on these):

- ``token first use, distinct``: ``GET /auth/me``, each request with its own new token
  (each one writes the token's ``last_used_at``);
- ``token first use, shared``: ``GET /auth/me``, all with one new token;
- ``anonymous tablet``: ``GET /tablets/{id}`` of the public tablet, no credentials;
- ``asset download, token``: the private model's asset (``GET /models/{id}/assets/{name}``)
  with one new token, the body checked for length.

Every request must be answered within ``--bound-s`` without a 5xx; then ``/health`` must
answer. Prints, per database, a table of throughput and latency per kind.

    .venv/bin/python bench/concurrency.py [--database sqlite postgresql] [--concurrency 200]
"""

from __future__ import annotations

import argparse
import asyncio
import hashlib
import os
import socket
import statistics
import subprocess
import sys
import tempfile
import time
import uuid
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path

import httpx

ROOT = Path(__file__).resolve().parent.parent
PG_ADMIN_DSN = "host=127.0.0.1 port=5432 user=postgres dbname=postgres"
PG_URL = "postgresql+psycopg://postgres@127.0.0.1:5432/{name}"
API = "/api/v1"
KINDS = (
    "token first use, distinct",
    "token first use, shared",
    "anonymous tablet",
    "asset download, token",
)
ASSET_NAME = "tablet.glb"


@dataclass(frozen=True)
class Seeded:
    """What :func:`seed` put in the database: ids and the secrets of never-used tokens."""

    public_tablet_id: int
    model_id: int
    asset_bytes: int
    fresh_tokens: tuple[str, ...]


def seed(url: str, storage_dir: Path, *, n_tokens: int, asset_bytes: int) -> Seeded:
    """Migrate ``url`` and add a museum, a staff user with ``n_tokens`` unused tokens, a
    public tablet and a private tablet with one model whose asset has ``asset_bytes``."""
    from backend import crud
    from backend.db import make_engine, make_sessionmaker, migrate, session_scope
    from backend.storage.local import LocalStorage
    from backend.tables import Job, JobKind, JobState, Model, Role, Scan

    migrate(url)
    data = os.urandom(asset_bytes)
    prefix = f"models/{uuid.uuid4().hex}"
    LocalStorage(storage_dir).put_bytes(f"{prefix}/{ASSET_NAME}", data)
    engine = make_engine(url)
    try:
        with session_scope(make_sessionmaker(engine)) as session:
            museum = crud.get_or_create_institution(session, name="Load Test Museum")
            user = crud.create_user(
                session, email="load@example.org", role=Role.staff, institution_id=museum.id
            )
            tokens = tuple(
                crud.create_token(session, user=user, name=f"load {i}")[1] for i in range(n_tokens)
            )
            public = crud.create_tablet(
                session, fields={"designation": "Public", "is_public": True}, institution_id=None
            )
            private = crud.create_tablet(
                session,
                fields={"designation": "Private", "is_public": False},
                institution_id=museum.id,
            )
            scan = Scan(
                tablet_id=private.id,
                face="obverse",
                scan_uid=uuid.uuid4().hex,
                bundle_key=f"bundles/{uuid.uuid4().hex}.zip",
                bundle_sha256="0" * 64,
                size_bytes=1,
                manifest={},
                user_id=user.id,
            )
            session.add(scan)
            session.flush()
            job = Job(
                tablet_id=private.id, scan_id=scan.id, kind=JobKind.reconstruct,
                state=JobState.succeeded,
            )  # fmt: skip
            session.add(job)
            session.flush()
            model = Model(
                tablet_id=private.id,
                scan_id=scan.id,
                job_id=job.id,
                version=1,
                storage_prefix=prefix,
                report={},
                assets={
                    ASSET_NAME: {
                        "size_bytes": asset_bytes,
                        "sha256": hashlib.sha256(data).hexdigest(),
                    }
                },
            )
            session.add(model)
            session.flush()
            return Seeded(public.id, model.id, asset_bytes, tokens)
    finally:
        engine.dispose()


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@contextmanager
def throwaway_postgres() -> Iterator[str]:
    """A new, empty PostgreSQL database on the local server, dropped afterwards."""
    import psycopg

    name = f"hammurabi_conc_{uuid.uuid4().hex[:10]}"
    with psycopg.connect(PG_ADMIN_DSN, autocommit=True) as conn:
        conn.execute(f'CREATE DATABASE "{name}"')
    try:
        yield PG_URL.format(name=name)
    finally:
        with psycopg.connect(PG_ADMIN_DSN, autocommit=True) as conn:
            conn.execute(f'DROP DATABASE IF EXISTS "{name}" WITH (FORCE)')


@contextmanager
def running_server(
    url: str, data_dir: Path, *, extra_env: dict | None = None
) -> Iterator[tuple[str, int]]:
    """``hammurabi serve`` on ``url`` at a free loopback port; yields (base URL, its pid)."""
    env = dict(
        os.environ,
        HAMMURABI_ENVIRONMENT="test",
        HAMMURABI_DATA_DIR=str(data_dir),
        HAMMURABI_DATABASE_URL=url,
        HAMMURABI_SECRET_KEY="concurrency-test-secret-" + "x" * 40,
        HAMMURABI_STORAGE_DIR=str(data_dir / "storage"),
        HAMMURABI_FRONTEND_DIST=str(data_dir / "no-frontend"),
        **(extra_env or {}),
    )
    port = free_port()
    log = open(data_dir / "server.log", "wb")  # noqa: SIM115 - closed below
    server = subprocess.Popen(
        [sys.executable, "-m", "backend.cli", "serve", "--port", str(port)]
        + ["--log-level", "warning"],
        env=env,
        cwd=ROOT,
        stdout=log,
        stderr=subprocess.STDOUT,
    )
    base = f"http://127.0.0.1:{port}"
    try:
        _wait_until_up(base, server, data_dir / "server.log")
        yield base, server.pid
    finally:
        server.terminate()
        try:
            server.wait(timeout=10)
        except subprocess.TimeoutExpired:  # a deadlocked server may not stop on SIGTERM
            server.kill()
            server.wait()
        log.close()


def _wait_until_up(base: str, server: subprocess.Popen, log: Path, deadline_s=60.0) -> None:
    start = time.monotonic()
    while time.monotonic() - start < deadline_s:
        if server.poll() is not None:
            raise RuntimeError(f"the server exited: {log.read_text()[-2000:]}")
        try:
            if httpx.get(f"{base}{API}/health", timeout=1).status_code == 200:
                return
        except httpx.HTTPError:
            time.sleep(0.2)
    raise RuntimeError("the server did not come up in 60 s")


@dataclass
class Burst:
    """The outcome of one burst: per request its status (None: no answer) and latency."""

    kind: str
    wall_s: float
    server_cpu_s: float = float("nan")
    statuses: list[int | None] = field(default_factory=list)
    latencies_ms: list[float] = field(default_factory=list)
    failures: list[str] = field(default_factory=list)

    @property
    def answered_ok(self) -> int:
        return sum(1 for s in self.statuses if s is not None and s < 500)

    def p(self, q: int) -> float:
        if len(self.latencies_ms) < 2:
            return self.latencies_ms[0] if self.latencies_ms else float("nan")
        return statistics.quantiles(self.latencies_ms, n=100, method="inclusive")[q - 1]


def requests_of(kind: str, seeded: Seeded, tokens: Iterator[str], n: int) -> list[tuple]:
    """``n`` requests ``(path, headers, expected body length or None)`` of ``kind``; token
    kinds take never-used tokens from ``tokens``."""
    if kind == "token first use, distinct":
        return [(f"{API}/auth/me", _bearer(next(tokens)), None) for _ in range(n)]
    if kind == "token first use, shared":
        return [(f"{API}/auth/me", _bearer(next(tokens)), None)] * n
    if kind == "anonymous tablet":
        return [(f"{API}/tablets/{seeded.public_tablet_id}", {}, None)] * n
    if kind == "asset download, token":
        path = f"{API}/models/{seeded.model_id}/assets/{ASSET_NAME}"
        return [(path, _bearer(next(tokens)), seeded.asset_bytes)] * n
    raise ValueError(f"kind: unknown {kind!r}")


def tokens_needed(n: int) -> int:
    """Fresh tokens a run of every kind with ``n`` requests per burst uses."""
    return n + 2


def _bearer(secret: str) -> dict[str, str]:
    return {"Authorization": f"Bearer {secret}"}


async def fire(base: str, kind: str, requests: list[tuple], *, bound_s: float) -> Burst:
    """All ``requests`` at once (one connection each); those unanswered after ``bound_s``
    are recorded with status None."""
    limits = httpx.Limits(max_connections=len(requests), max_keepalive_connections=0)
    timeout = httpx.Timeout(bound_s, connect=bound_s)
    burst = Burst(kind=kind, wall_s=0.0)
    async with httpx.AsyncClient(base_url=base, limits=limits, timeout=timeout) as client:

        async def one(path: str, headers: dict, length: int | None):
            start = time.perf_counter()
            try:
                response = await client.get(path, headers=headers)
            except httpx.HTTPError as exc:
                burst.statuses.append(None)
                burst.failures.append(f"{type(exc).__name__}: {exc}")
                return
            burst.latencies_ms.append((time.perf_counter() - start) * 1000)
            burst.statuses.append(response.status_code)
            if response.status_code != 200:
                burst.failures.append(f"{response.status_code}: {response.text[:200]}")
            elif length is not None and len(response.content) != length:
                burst.failures.append(f"body of {len(response.content)} bytes, not {length}")

        start = time.perf_counter()
        tasks = [asyncio.ensure_future(one(*r)) for r in requests]
        _done, pending = await asyncio.wait(tasks, timeout=bound_s)
        for task in pending:  # pragma: no cover - only when the server hangs
            task.cancel()
            burst.statuses.append(None)
            burst.failures.append(f"no answer within {bound_s:.0f} s")
        burst.wall_s = time.perf_counter() - start
    return burst


def cpu_seconds(pid: int) -> float:
    """User + system CPU time of process ``pid`` (Linux /proc; one uvicorn process)."""
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def health_answers(base: str, *, timeout_s: float = 10.0) -> bool:
    try:
        return httpx.get(f"{base}{API}/health", timeout=timeout_s).status_code == 200
    except httpx.HTTPError:
        return False


def run_scenario(
    url: str, data_dir: Path, *, concurrency: int, asset_bytes: int, bound_s: float
) -> tuple[list[Burst], bool]:
    """Seed ``url``, start the server and fire one burst of each kind; returns the bursts
    and whether /health answered afterwards."""
    seeded = seed(
        url, data_dir / "storage", n_tokens=tokens_needed(concurrency), asset_bytes=asset_bytes
    )
    tokens = iter(seeded.fresh_tokens)
    bursts = []
    with running_server(url, data_dir) as (base, pid):
        for kind in KINDS:
            requests = requests_of(kind, seeded, tokens, concurrency)
            cpu_before = cpu_seconds(pid)
            burst = asyncio.run(fire(base, kind, requests, bound_s=bound_s))
            burst.server_cpu_s = cpu_seconds(pid) - cpu_before
            bursts.append(burst)
        healthy = health_answers(base)
    return bursts, healthy


def table(database: str, bursts: list[Burst]) -> str:
    rows = [
        f"| {database} | kind | answered < 500 | 5xx or none | requests/s | p50 (ms) | "
        "p95 (ms) | max (ms) | server CPU / req (ms) |",
        "|---|---|---:|---:|---:|---:|---:|---:|---:|",
    ]
    for b in bursts:
        n = len(b.statuses)
        rows.append(
            f"| {database} | {b.kind} | {b.answered_ok}/{n} | {n - b.answered_ok} | "
            f"{n / b.wall_s:.0f} | {b.p(50):.0f} | {b.p(95):.0f} | "
            f"{max(b.latencies_ms, default=float('nan')):.0f} | "
            f"{b.server_cpu_s * 1000 / n:.1f} |"
        )
    return "\n".join(rows)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument(
        "--database", nargs="+", choices=["sqlite", "postgresql"], default=["sqlite", "postgresql"]
    )
    parser.add_argument("--concurrency", type=int, default=200, help="requests per burst")
    parser.add_argument("--asset-mb", type=float, default=3.0, help="size of the asset")
    parser.add_argument("--bound-s", type=float, default=60.0, help="time allowed per burst")
    args = parser.parse_args()
    if args.concurrency < 1:
        parser.error("--concurrency must be at least 1")
    asset_bytes = int(args.asset_mb * 1024 * 1024)
    failed = False
    for database in args.database:
        with tempfile.TemporaryDirectory(prefix="bench_concurrency_") as tmp:
            data_dir = Path(tmp)
            if database == "sqlite":
                url = f"sqlite:///{data_dir / 'hammurabi.db'}"
                bursts, healthy = run_scenario(
                    url, data_dir, concurrency=args.concurrency, asset_bytes=asset_bytes,
                    bound_s=args.bound_s,
                )  # fmt: skip
            else:
                with throwaway_postgres() as url:
                    bursts, healthy = run_scenario(
                        url, data_dir, concurrency=args.concurrency, asset_bytes=asset_bytes,
                        bound_s=args.bound_s,
                    )  # fmt: skip
        print(table(database, bursts))
        print(f"/health afterwards: {'answered' if healthy else 'NO ANSWER'}\n")
        failed |= not healthy or any(b.answered_ok < len(b.statuses) for b in bursts)
        for b in bursts:
            for failure in sorted(set(b.failures))[:3]:
                print(f"  {b.kind}: {failure}")
    print(
        f"{args.concurrency} concurrent requests per burst, asset {asset_bytes} bytes, "
        f"load average {os.getloadavg()[0]:.1f}"
    )
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
