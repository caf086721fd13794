"""Load benchmark of catalogue search: the whole ORACC extract, 50 concurrent clients.

Starts the library service (``hammurabi serve``, one uvicorn process) on a free loopback port
in a subprocess, on a fresh SQLite file (or a throwaway PostgreSQL database with
``--database postgresql``) holding the 7,524 records of /work/shared/data/oracc-catalogue,
then lets ``--clients`` httpx async clients issue filtered search pages (text + filter +
facets, JSON) until ``--requests`` are done or ``--seconds`` have passed. Prints a table:
p50/p95/max latency (ms) and requests/s per query kind.

    .venv/bin/python bench/search_load.py [--database sqlite|postgresql] [--clients 50]
"""

from __future__ import annotations

import argparse
import asyncio
import os
import random
import socket
import statistics
import subprocess
import sys
import tempfile
import time
import urllib.parse
import uuid
from pathlib import Path

import httpx

ROOT = Path(__file__).resolve().parent.parent
CATALOGUE = Path("/work/shared/data/oracc-catalogue/oracc_catalogue_merged.csv")
PG_ADMIN_DSN = "host=127.0.0.1 port=5432 user=postgres dbname=postgres"

# A filtered search page as the library page issues it: a facet filter, maybe some text,
# facets counted, 25 rows.
QUERIES = {
    "filter only": [
        {"period": "Neo-Assyrian"},
        {"genre": "royal inscription"},
        {"provenience": "Nineveh (Kuyunjik)"},
        {"period": "Old Babylonian", "genre": "lexical"},
    ],
    "text + filter": [
        {"q": "K", "period": "Neo-Assyrian"},
        {"q": "BM 1", "period": "Old Babylonian"},
        {"q": "SAA", "genre": "letter"},
        {"q": "VAT", "provenience": "Assur (mod. Qalat Sherqat)"},
    ],
    "text only": [{"q": "P33"}, {"q": "YBC"}, {"q": "ATU 5"}, {"q": "CT 13"}],
}


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def run(cmd: list[str], env: dict[str, str]) -> None:
    subprocess.run(cmd, env=env, check=True, cwd=ROOT)


def _stat(pid: int) -> list[str]:
    return Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()


def cpu_seconds(pid: int) -> float:
    """User + system CPU time of a process and its children (uvicorn workers), Linux /proc."""
    pids = [pid]
    for entry in Path("/proc").iterdir():
        if entry.name.isdigit():
            try:
                if int(_stat(int(entry.name))[1]) == pid:
                    pids.append(int(entry.name))
            except (FileNotFoundError, ProcessLookupError):
                continue
    total = 0
    for p in pids:
        try:
            fields = _stat(p)
        except FileNotFoundError:
            continue
        total += int(fields[11]) + int(fields[12])
    return total / os.sysconf("SC_CLK_TCK")


def wait_until_up(base: str, deadline_s: float = 60.0) -> None:
    start = time.monotonic()
    while time.monotonic() - start < deadline_s:
        try:
            if httpx.get(f"{base}/api/v1/health", timeout=1).status_code == 200:
                return
        except httpx.HTTPError:
            time.sleep(0.2)
    raise SystemExit("the server did not come up")


async def client_loop(client, base, queue, results, retries, stop_at):
    while time.monotonic() < stop_at:
        try:
            kind, params = queue.pop()
        except IndexError:
            return
        start = time.perf_counter()
        try:
            response = await client.get(f"{base}/api/v1/tablets", params=params)
        except (httpx.RemoteProtocolError, httpx.ReadError):
            # uvicorn closes keep-alive connections idle for 5 s; a request sent on one at
            # that moment is lost (a client-side race under heavy load): send it again, and
            # count it (with the time of both attempts).
            retries.append(kind)
            response = await client.get(f"{base}/api/v1/tablets", params=params)
        elapsed_ms = (time.perf_counter() - start) * 1000
        if response.status_code != 200:
            raise SystemExit(f"search {params} failed: {response.status_code} {response.text}")
        results.append((kind, elapsed_ms))


async def load(base: str, *, clients: int, requests: int, seconds: float):
    rng = random.Random(0)
    queue = [
        (kind, dict(params, page=rng.randint(1, 3)))
        for kind, params in (
            (k, rng.choice(QUERIES[k])) for k in rng.choices(list(QUERIES), k=requests)
        )
    ]
    results: list[tuple[str, float]] = []
    retries: list[str] = []
    limits = httpx.Limits(max_connections=clients, max_keepalive_connections=clients)
    async with httpx.AsyncClient(limits=limits, timeout=60) as client:
        # warm-up: one of each, not counted
        for params_list in QUERIES.values():
            for params in params_list:
                await client.get(f"{base}/api/v1/tablets", params=params)
        start = time.perf_counter()
        stop_at = time.monotonic() + seconds
        await asyncio.gather(
            *(client_loop(client, base, queue, results, retries, stop_at) for _ in range(clients))
        )
        wall_s = time.perf_counter() - start
    return results, wall_s, retries


WRK_SCRIPT = """
paths = {%s}
i = 0
request = function()
  i = i %% #paths + 1
  return wrk.format("GET", paths[i])
end
done = function(summary, latency, requests)
  local e = summary.errors
  io.write(string.format(
    "| wrk (all kinds, in turn) | %%d | %%.1f | %%.1f | %%.1f |\\n\\n" ..
    "%%d requests in %%.1f s: %%.0f requests/s; errors %%d, non-2xx %%d\\n",
    summary.requests, latency:percentile(50) / 1000, latency:percentile(95) / 1000,
    latency.max / 1000, summary.requests, summary.duration / 1e6,
    summary.requests / (summary.duration / 1e6),
    e.connect + e.read + e.write + e.timeout, e.status))
end
"""


def run_wrk(base: str, *, clients: int, seconds: float, tmp: str) -> None:
    """The same pages from ``wrk`` (C, one thread): a load generator that leaves the CPU to
    the server (the httpx clients cost more CPU per request than the server does)."""
    paths = [
        f"/api/v1/tablets?{urllib.parse.urlencode(dict(params, page=page))}"
        for params_list in QUERIES.values()
        for params in params_list
        for page in (1, 2, 3)
    ]
    script = Path(tmp) / "search.lua"
    script.write_text(WRK_SCRIPT % ", ".join(f'"{p}"' for p in paths))
    print("| query | requests | p50 (ms) | p95 (ms) | max (ms) |\n|---|---:|---:|---:|---:|")
    sys.stdout.flush()
    cmd = ["wrk", "-t1", f"-c{clients}", "-s", str(script), base]
    # warm-up (every page rendered once), not counted
    subprocess.run([*cmd, "-d3s"], check=True, stdout=subprocess.DEVNULL)
    out = subprocess.run(
        [*cmd, f"-d{int(seconds)}s"], check=True, stdout=subprocess.PIPE, text=True
    )
    out = out.stdout
    print(out[out.index("| wrk") :].rstrip() if "| wrk" in out else out)


def percentile(values: list[float], q: float) -> float:
    return statistics.quantiles(values, n=100, method="inclusive")[int(q) - 1]


def table(results, wall_s, clients) -> str:
    rows = ["| query | requests | p50 (ms) | p95 (ms) | max (ms) |", "|---|---:|---:|---:|---:|"]
    kinds = sorted({k for k, _ in results})
    for kind in [*kinds, "all"]:
        values = [ms for k, ms in results if kind in (k, "all")]
        rows.append(
            f"| {kind} | {len(values)} | {percentile(values, 50):.1f} | "
            f"{percentile(values, 95):.1f} | {max(values):.1f} |"
        )
    rows.append("")
    rows.append(f"{len(results)} requests by {clients} clients in {wall_s:.1f} s: "
                f"{len(results) / wall_s:.0f} requests/s")  # fmt: skip
    return "\n".join(rows)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--database", choices=["sqlite", "postgresql"], default="sqlite")
    parser.add_argument("--clients", type=int, default=50)
    parser.add_argument("--requests", type=int, default=2000)
    parser.add_argument("--seconds", type=float, default=60.0)
    parser.add_argument("--workers", type=int, default=1, help="server processes")
    parser.add_argument(
        "--wrk",
        action="store_true",
        help="load from wrk (apt-get install wrk) instead of httpx: a short warm-up run, "
        "then --seconds of load",
    )
    args = parser.parse_args()

    with tempfile.TemporaryDirectory(prefix="search_load_") as tmp:
        env = dict(os.environ, HAMMURABI_DATA_DIR=tmp, HAMMURABI_ENVIRONMENT="development")
        pg_name = None
        if args.database == "postgresql":
            import psycopg

            pg_name = f"hammurabi_bench_{uuid.uuid4().hex[:10]}"
            with psycopg.connect(PG_ADMIN_DSN, autocommit=True) as conn:
                conn.execute(f'CREATE DATABASE "{pg_name}"')
            env["HAMMURABI_DATABASE_URL"] = f"postgresql+psycopg://postgres@127.0.0.1/{pg_name}"
        cli = [sys.executable, "-m", "backend.cli"]
        try:
            t0 = time.perf_counter()
            run([*cli, "import-catalogue", str(CATALOGUE), "--public"], env)
            import_s = time.perf_counter() - t0
            port = free_port()
            server = subprocess.Popen(
                [
                    *cli,
                    "serve",
                    "--port",
                    str(port),
                    "--log-level",
                    "warning",
                    "--workers",
                    str(args.workers),
                ],
                env=env,
                cwd=ROOT,
            )
            try:
                base = f"http://127.0.0.1:{port}"
                wait_until_up(base)
                if args.wrk:
                    print(f"database: {args.database}; load from wrk, {args.clients} connections")
                    run_wrk(base, clients=args.clients, seconds=args.seconds, tmp=tmp)
                    print(f"load average {os.getloadavg()[0]:.1f}")
                    return 0
                cpu_before = cpu_seconds(server.pid)
                client_before = time.process_time()
                results, wall_s, retries = asyncio.run(
                    load(base, clients=args.clients, requests=args.requests, seconds=args.seconds)
                )
                # includes the uncounted warm-up requests (12): a slight overestimate
                cpu_ms = (cpu_seconds(server.pid) - cpu_before) * 1000 / len(results)
                client_ms = (time.process_time() - client_before) * 1000 / len(results)
            finally:
                server.terminate()
                try:
                    server.wait(timeout=60)
                except subprocess.TimeoutExpired:
                    server.kill()
                    server.wait()
        finally:
            if pg_name:
                with psycopg.connect(PG_ADMIN_DSN, autocommit=True) as conn:
                    conn.execute(f'DROP DATABASE IF EXISTS "{pg_name}" WITH (FORCE)')
    print(f"database: {args.database}; catalogue import (CLI, incl. start-up): {import_s:.1f} s")
    print(table(results, wall_s, args.clients))
    print(f"requests sent again after a dropped keep-alive connection: {len(retries)}")
    print(f"server CPU time per request: {cpu_ms:.1f} ms (load average {os.getloadavg()[0]:.1f})")
    # The clients share the machine with the server: their CPU is not the server's to use.
    print(f"client (this process) CPU time per request: {client_ms:.1f} ms")
    return 0


if __name__ == "__main__":
    sys.exit(main())
