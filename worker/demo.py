"""``make demo``: the whole system on the embedded default, from catalogue to relightable model.

1. a fresh data directory (SQLite, local storage, the embedded broker: no server needed);
2. the real ORACC catalogue imported (``../shared/data/oracc-catalogue`` next to the repo, or
   ``HAMMURABI_DEMO_CATALOGUE``; without it a one-record catalogue, said clearly);
3. ``hammurabi serve`` and ``hammurabi worker`` started as real processes;
4. the six faces of a small tablet (``--tablet-mm``, default 14 × 11 × 7 mm) simulated
   (``worker.simulate``, quick preset) at the paper's resolution, 26.8 µm per pixel, each
   face's frame following the tablet (about 640 × 530 px for the obverse; ``--pixel-um``
   chooses a coarser pixel, e.g. for CI), two faces at a time; each bundle marked
   ``scan.tablet.simulated = "true"`` (free metadata, SCAN_BUNDLE.md) and the six uploaded
   together through the API by the rig agent's spool and upload client, like a rig;
5. a worker started once the six are in (two reconstructions at a time), the
   reconstructions followed on the job rows (a progress line per face), then the worker's
   automatic registration of the six faces, started once, when the last face is
   reconstructed (whole tablet, fatcross plates);
6. the library's address, the whole tablet's link and a staff login printed; serving until
   Ctrl-C (``--exit-when-ready``: stop once the models are ready, for tests).

``LocalLibrary`` (start/stop the service and workers, the CLI, an API token) is reused by
the system tests and ``bench/queue.py``.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import secrets
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import time
import zipfile
from collections.abc import Callable
from concurrent.futures import ProcessPoolExecutor, as_completed
from pathlib import Path

import httpx

REPO = Path(__file__).resolve().parent.parent
CATALOGUE_FILE = "oracc_catalogue_merged.csv"
# Upload order (every prefix of it overlaps: the edges join obverse and reverse).
DEMO_FACES = ("obverse", "top", "bottom", "left", "right", "reverse")
# A small tablet (mm): at the paper's 26.8 µm per pixel its six faces simulate, reconstruct
# and register within about five minutes on two cores (docs/benchmarks.md, "make demo").
DEMO_TABLET_MM = (14.0, 11.0, 7.0)
DEMO_STALE_AFTER_S = 600
FALLBACK_CATALOGUE = (
    "key,designation,museum_no,period,provenience,genre,language\n"
    "P000001,Demo tablet,Demo 1,Old Babylonian,Sippar,legal,Akkadian\n"
)


def free_port() -> int:
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return sock.getsockname()[1]


def find_catalogue() -> Path | None:
    """The ORACC catalogue CSV: $HAMMURABI_DEMO_CATALOGUE, ../shared/data next to the repo."""
    candidates = []
    if os.environ.get("HAMMURABI_DEMO_CATALOGUE"):
        candidates.append(Path(os.environ["HAMMURABI_DEMO_CATALOGUE"]))
    candidates += [
        REPO.parent / "shared" / "data" / "oracc-catalogue",
        Path("/work/shared/data/oracc-catalogue"),
    ]
    for path in candidates:
        if path.is_file():
            return path
        if (path / CATALOGUE_FILE).is_file():
            return path / CATALOGUE_FILE
    return None


class LocalLibrary:
    """The library service and its workers as subprocesses on one data directory.

    ``env`` adds HAMMURABI_* settings (e.g. a Redis broker); without it everything is the
    embedded default. Workers run in their own process group so a test can SIGKILL one
    worker with its pool children, like a machine that dies.
    """

    def __init__(self, data_dir: Path, *, env: dict[str, str] | None = None, port: int = 0):
        self.data_dir = Path(data_dir).resolve()
        self.port = port or free_port()
        self.env = {
            **{k: v for k, v in os.environ.items() if not k.startswith("HAMMURABI_")},
            "HAMMURABI_DATA_DIR": str(self.data_dir),
            "HAMMURABI_ENVIRONMENT": "development",
            # A fresh random key per demo: nothing signing sessions comes from the source tree.
            "HAMMURABI_SECRET_KEY": secrets.token_urlsafe(48),
            "PYTHONUNBUFFERED": "1",
            # The service and the workers run this checkout's code, whatever the virtual
            # environment's editable install points to (they start in the data directory).
            "PYTHONPATH": os.pathsep.join(
                [str(REPO), *filter(None, [os.environ.get("PYTHONPATH")])]
            ),
            **(env or {}),
        }
        self.server: subprocess.Popen | None = None
        self.workers: list[subprocess.Popen] = []
        self.logs = self.data_dir / "logs"
        self.logs.mkdir(parents=True, exist_ok=True)
        self.token: str | None = None
        self._log_files: list = []

    @property
    def url(self) -> str:
        return f"http://127.0.0.1:{self.port}"

    def cli(
        self, *args: str, check: bool = True, stdin: str | None = None
    ) -> subprocess.CompletedProcess:
        result = subprocess.run(
            [sys.executable, "-m", "backend.cli", *args],
            env=self.env,
            cwd=self.data_dir,
            input=stdin,
            capture_output=True,
            text=True,
            timeout=300,
        )
        if check and result.returncode != 0:
            raise RuntimeError(f"hammurabi {args[0]} failed: {result.stderr.strip()}")
        return result

    def create_admin_token(self, email: str = "demo@example.org") -> str:
        self.cli("create-user", email, "--role", "admin", "--no-password")
        self.token = self.cli("create-token", email, "--name", "demo rig").stdout.strip()
        return self.token

    def _spawn(self, args: list[str], log_name: str) -> subprocess.Popen:
        log = open(self.logs / log_name, "ab")  # noqa: SIM115 (lives as long as the process)
        self._log_files.append(log)
        return subprocess.Popen(
            [sys.executable, "-m", "backend.cli", *args],
            env=self.env,
            cwd=self.data_dir,
            stdout=log,
            stderr=subprocess.STDOUT,
            start_new_session=True,
        )

    def start_server(self, timeout_s: float = 60.0) -> None:
        self.server = self._spawn(
            ["serve", "--port", str(self.port), "--log-level", "warning"], "server.log"
        )
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            if self.server.poll() is not None:
                raise RuntimeError(f"the service exited; see {self.logs / 'server.log'}")
            try:
                if httpx.get(f"{self.url}/api/v1/health", timeout=2).status_code == 200:
                    return
            except httpx.TransportError:
                pass
            time.sleep(0.2)
        raise RuntimeError(f"the service did not answer in {timeout_s:.0f} s")

    def start_worker(self, name: str | None = None, *, concurrency: int = 1) -> subprocess.Popen:
        name = name or f"w{len(self.workers) + 1}"
        args = ["worker", "--hostname", f"{name}@%h", "--concurrency", str(concurrency)]
        proc = self._spawn(args, f"worker-{name}.log")
        self.workers.append(proc)
        return proc

    def kill_worker(self, proc: subprocess.Popen, sig: int = signal.SIGKILL) -> None:
        """Signal the worker's whole process group (main process and pool children)."""
        with contextlib.suppress(ProcessLookupError):
            os.killpg(proc.pid, sig)
        proc.wait(30)
        if proc in self.workers:
            self.workers.remove(proc)

    def stop(self) -> None:
        for proc in [*self.workers, self.server]:
            if proc is not None and proc.poll() is None:
                try:
                    os.killpg(proc.pid, signal.SIGTERM)
                except ProcessLookupError:
                    continue
        for proc in [*self.workers, self.server]:
            if proc is None:
                continue
            try:
                proc.wait(20)
            except subprocess.TimeoutExpired:
                os.killpg(proc.pid, signal.SIGKILL)
                proc.wait(10)
        self.workers = []
        self.server = None
        for log in self._log_files:
            log.close()
        self._log_files = []

    def client(self, token: str | None = None) -> httpx.Client:
        """A client on ``/api/v1`` with ``token`` (default: the admin token)."""
        return httpx.Client(
            base_url=f"{self.url}/api/v1",
            headers={"Authorization": f"Bearer {token or self.token}"},
            timeout=60,
        )

    def upload_bundle_zip(self, zip_path: Path, *, tablet_id: int) -> dict:
        """Upload like a rig: a spool entry holding the bundle, the rig agent's client."""
        from rig_agent.spool import Spool
        from rig_agent.upload import LibraryClient, upload_scan

        spool = Spool(self.data_dir / "rig-spool")
        scan = spool.create(kind="scan", shots=[], meta={"demo": True})
        shutil.copyfile(zip_path, scan.path / "bundle.zip")
        scan.update_state(phase="ready", bundle="bundle.zip")
        client = LibraryClient(self.url, self.token or "")
        try:
            return upload_scan(scan, client, tablet_id=tablet_id)
        finally:
            client.close()

    def wait_tablet_model(self, tablet_id: int, *, timeout_s: float, scans: int = 0) -> dict | None:
        """Poll until the worker's automatic registration has stored a whole-tablet model of
        at least ``scans`` scans (a registration that started while faces were still being
        reconstructed holds fewer; the worker queues another for the rest)."""
        deadline = time.monotonic() + timeout_s
        with self.client() as http:
            while time.monotonic() < deadline:
                models = http.get("/models", params={"tablet_id": tablet_id})
                done = [
                    m
                    for m in models.raise_for_status().json()
                    if len((m.get("report") or {}).get("scans") or []) >= scans
                ]
                if done:
                    return done[-1]
                if self.workers and all(w.poll() is not None for w in self.workers):
                    raise RuntimeError(f"every worker exited; see {self.logs}")
                time.sleep(0.5)
        return None

    def wait_jobs(
        self,
        job_ids: list[int],
        *,
        timeout_s: float,
        on_poll: Callable[[list[dict]], None] | None = None,
    ) -> list[dict]:
        """Poll until every job has finished; returns their rows (JSON)."""
        deadline = time.monotonic() + timeout_s
        with self.client() as http:
            while True:
                rows = [http.get(f"/jobs/{j}").raise_for_status().json() for j in job_ids]
                if on_poll:
                    on_poll(rows)
                if all(r["state"] in ("succeeded", "failed") for r in rows):
                    return rows
                if self.workers and all(w.poll() is not None for w in self.workers):
                    raise RuntimeError(f"every worker exited; see {self.logs}")
                if time.monotonic() > deadline:
                    raise TimeoutError(f"jobs not finished after {timeout_s:.0f} s: {rows}")
                time.sleep(0.3)


def simulate_face_zip(
    out_dir: Path,
    face: str,
    *,
    seed: int,
    tablet_mm: tuple[float, float, float] = DEMO_TABLET_MM,
    pixel_um: float = 26.8,
) -> Path:
    """Simulate one face of a ``tablet_mm`` tablet at ``pixel_um`` (quick preset; the frame
    follows the tablet) and zip its bundle, marked simulated; the simulator's files are
    removed once zipped."""
    from worker.simulate import simulate_scan

    result = simulate_scan(
        out_dir / face,
        seed=seed,
        face=face,
        preset="quick",
        tablet_mm=tablet_mm,
        pixel_size_um=pixel_um,
    )
    plain = Path(shutil.make_archive(str(out_dir / f"{face}-plain"), "zip", result.bundles[face]))
    zipped = rewrite_manifest(plain, out_dir / f"{face}-bundle.zip", mark_simulated)
    plain.unlink()
    shutil.rmtree(out_dir / face, ignore_errors=True)
    return zipped


def mark_simulated(manifest: dict) -> None:
    """``scan.tablet.simulated = "true"``: SCAN_BUNDLE.md's free metadata, read back by
    :func:`worker.bundle.is_simulated` so that the API, the pages and the plates say so."""
    manifest["scan"].setdefault("tablet", {})["simulated"] = "true"


def rewrite_manifest(zip_path: Path, out: Path, change: Callable[[dict], None]) -> Path:
    """A copy of the bundle ZIP whose manifest.json ``change`` edits in place (the frames are
    copied byte for byte)."""
    with zipfile.ZipFile(zip_path) as src, zipfile.ZipFile(out, "w") as dst:
        for info in src.infolist():
            data = src.read(info)
            if info.filename == "manifest.json":
                manifest = json.loads(data)
                change(manifest)
                data = json.dumps(manifest).encode()
            dst.writestr(info, data)
    return out


def bundle_zip_as_new_scan(zip_path: Path, n: int, directory: Path) -> Path:
    """The same bundle ZIP as another scan (manifest scan.id + "-n"): uploading it makes a new
    scan and a new job. For load and queue tests that need many distinct scans cheaply."""

    def renamed(manifest: dict) -> None:
        manifest["scan"]["id"] += f"-{n}"

    return rewrite_manifest(zip_path, directory / f"bundle-{n}.zip", renamed)


def port_is_free(port: int) -> bool:
    """Whether 127.0.0.1:``port`` can be listened on now (as uvicorn does: SO_REUSEADDR, so a
    port left in TIME_WAIT by the last run counts as free, one being listened on does not)."""
    with socket.socket() as sock:
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        try:
            sock.bind(("127.0.0.1", port))
        except OSError:
            return False
    return True


class Progress:
    """One status line per step; a live line for job progress when stdout is a terminal."""

    def __init__(self, total_steps: int):
        self.total = total_steps
        self.step = 0
        self.tty = sys.stdout.isatty()
        self.t0 = time.monotonic()
        self._last = ""

    def say(self, text: str) -> None:
        self.step += 1
        print(
            f"[{self.step}/{self.total}] {text}  ({time.monotonic() - self.t0:.0f} s)", flush=True
        )

    def jobs(self, rows: list[dict], faces: list[str]) -> None:
        parts = [f"{face}: {_job_text(r)}" for face, r in zip(faces, rows, strict=True)]
        line = "      " + " | ".join(parts)
        if self.tty:
            print("\r" + line.ljust(len(self._last)), end="", flush=True)
        elif line != self._last:
            print(line, flush=True)
        self._last = line


def _check_ready(library: LocalLibrary, url: str, model_id: int) -> int:
    """The viewer page and the model's assets answer (what a browser would fetch first)."""
    page = httpx.get(url, timeout=30)
    with library.client() as http:
        model = http.get(f"/models/{model_id}").raise_for_status().json()
    glb = httpx.get(f"{library.url}{model['assets']['model.glb']}", timeout=30)
    ok = page.status_code == 200 and glb.status_code == 200 and glb.content[:4] == b"glTF"
    print(f"CHECK viewer page {page.status_code}, model.glb {glb.status_code}", flush=True)
    return 0 if ok else 1


def _job_text(row: dict) -> str:
    if row["state"] == "running":
        return f"{row['stage']} {100 * row['progress']:.0f}%"
    return row["state"]


STAFF_EMAIL = "staff@demo.example"
DEMO_INSTITUTION = "Demo"
# The demo institution's default licence and credit: without them the manifests have no
# ``rights`` and the tablet page says "Licence: none stated" (docs/api.md, "Licences").
DEMO_LICENCE = "https://creativecommons.org/licenses/by/4.0/"
DEMO_ATTRIBUTION = "Digital Hammurabi demo (simulated scans)"


def set_institution_licence(
    http: httpx.Client, *, name: str, licence: str, attribution: str
) -> dict:
    """Set the default licence and attribution of the institution ``name`` through the API,
    as its staff would (``http``: a client on ``/api/v1`` with a staff token); returns the
    institution as the API answers it."""
    institutions = http.get("/institutions").raise_for_status().json()
    matches = [i for i in institutions if i["name"] == name]
    if not matches:
        raise RuntimeError(f"no institution {name!r} in the library")
    response = http.patch(
        f"/institutions/{matches[0]['id']}",
        json={"licence": licence, "attribution": attribution},
    )
    return response.raise_for_status().json()


def run_demo(args: argparse.Namespace) -> int:
    if not 1 <= args.port <= 65535:
        print(f"demo: --port must be 1..65535, got {args.port}", file=sys.stderr)
        return 2
    if not port_is_free(args.port):
        print(
            f"demo: port {args.port} on 127.0.0.1 is in use (another demo or service?); "
            f"stop it, or choose another port: make demo PORT={args.port + 123}",
            file=sys.stderr,
        )
        return 2
    from worker.simulate.tablet import check_size_mm

    try:
        check_size_mm(args.tablet_mm)
    except ValueError as exc:
        print(f"demo: --tablet-mm: {exc}", file=sys.stderr)
        return 2
    if not 5.0 <= args.pixel_um <= 1000.0:
        print(f"demo: --pixel-um must be 5..1000 µm, got {args.pixel_um:g}", file=sys.stderr)
        return 2
    if not (1 <= args.jobs <= 16 and 1 <= args.concurrency <= 16):
        print("demo: --jobs and --concurrency must be 1..16", file=sys.stderr)
        return 2
    pixel_um = args.pixel_um
    progress = Progress(total_steps=6)
    data_dir = Path(args.data_dir).resolve()
    if data_dir.exists():
        shutil.rmtree(data_dir)
    data_dir.mkdir(parents=True)
    # A running job whose heartbeat is this old is taken over by another worker process.
    # The default (15 s) suits servers; on a busy one-machine demo a long registration step
    # can starve its heartbeat thread for longer, and with two worker processes the other
    # one then takes the registration over and starts it again, over and over.
    library = LocalLibrary(
        data_dir, port=args.port, env={"HAMMURABI_JOB_STALE_AFTER_S": str(DEMO_STALE_AFTER_S)}
    )
    try:
        catalogue = find_catalogue()
        if catalogue is None:
            catalogue = data_dir / "demo-catalogue.csv"
            catalogue.write_text(FALLBACK_CATALOGUE, encoding="utf-8")
            progress.say(
                "the ORACC catalogue was not found (looked in ../shared/data/oracc-catalogue "
                "and $HAMMURABI_DEMO_CATALOGUE): importing a one-record demo catalogue instead"
            )
        else:
            progress.say(f"importing the catalogue {catalogue} (SQLite in {data_dir})")
        library.cli(
            "import-catalogue", str(catalogue), "--public", "--institution", DEMO_INSTITUTION
        )
        library.create_admin_token()
        staff_password = secrets.token_urlsafe(9)
        library.cli(
            "create-user",
            STAFF_EMAIL,
            "--role",
            "staff",
            "--institution",
            DEMO_INSTITUTION,
            "--password-stdin",
            stdin=staff_password + "\n",
        )

        progress.say("starting the library service (embedded broker)")
        library.start_server()
        staff_token = library.cli(
            "create-token", STAFF_EMAIL, "--name", "demo licence"
        ).stdout.strip()
        with library.client(token=staff_token) as http:
            set_institution_licence(
                http, name=DEMO_INSTITUTION, licence=DEMO_LICENCE, attribution=DEMO_ATTRIBUTION
            )
        print(
            f"      licence of {DEMO_INSTITUTION}'s records: {DEMO_LICENCE}, "
            f'"{DEMO_ATTRIBUTION}" (set by its staff through the API)'
        )

        with library.client() as http:
            items = http.get("/tablets", params={"page_size": 1, "sort": "designation"})
            tablet = items.raise_for_status().json()["items"][0]
        paper = " (the paper's)" if abs(pixel_um - 26.8) < 0.05 else ""
        size = "×".join(f"{v:g}" for v in args.tablet_mm)
        progress.say(
            f"simulating the six faces of a {size} mm tablet (a SIMULATED scan, labelled so) "
            f"for {tablet['designation']}: quick preset, {pixel_um:g} µm per pixel{paper}, "
            f"{args.jobs} faces at a time; then the six are uploaded together through the API "
            "with the rig agent's upload client, like a rig"
        )
        work = Path(tempfile.mkdtemp(prefix="demo-sim-", dir=data_dir))
        bundles = simulate_faces(work, args, pixel_um)
        faces, job_ids = [], []
        for face in DEMO_FACES:
            t1 = time.monotonic()
            result = library.upload_bundle_zip(bundles[face], tablet_id=tablet["id"])
            bundles[face].unlink()
            faces.append(face)
            job_ids.append(result["job"]["id"])
            print(
                f"      {face}: uploaded in {time.monotonic() - t1:.0f} s "
                f"(job {result['job']['id']})",
                flush=True,
            )
        shutil.rmtree(work, ignore_errors=True)

        # The worker starts once the six are in: it then finds them all queued, so the
        # registration (which waits for the tablet's pending reconstructions) runs once, on
        # all six, however fast a reconstruction is. Two at a time: the machine has two cores.
        progress.say(
            f"reconstructing {len(job_ids)} scans on a reconstruction worker started now "
            f"({args.concurrency} at a time)"
        )
        library.start_worker("demo", concurrency=args.concurrency)
        rows = library.wait_jobs(
            job_ids, timeout_s=args.timeout, on_poll=lambda r: progress.jobs(r, faces)
        )
        print()
        failed = [f"{f}: {r['error']}" for f, r in zip(faces, rows, strict=True) if r["error"]]
        if failed:
            print("demo: some reconstructions failed:\n  " + "\n  ".join(failed), file=sys.stderr)
            return 1
        progress.say(
            "registering the six faces into one tablet on the worker (automatic, once the "
            "last face is reconstructed)"
        )
        whole = library.wait_tablet_model(tablet["id"], timeout_s=args.timeout, scans=len(job_ids))
        if whole is None:
            print(
                f"demo: the whole-tablet registration did not finish in {args.timeout:.0f} s; "
                f"the faces are shown one by one (logs in {library.logs})",
                file=sys.stderr,
            )
        else:
            print(f"      whole tablet: model {whole['id']}", flush=True)
        shown = whole["id"] if whole is not None else rows[0]["model_id"]
        url = f"{library.url}/tablet.html?id={tablet['id']}#m={shown}"
        progress.say(f"ready: open {url}")
        print(f"      the library: {library.url}/", flush=True)
        what = "the whole tablet" if whole is not None else "the obverse"
        print(f"      {what} (simulated scan): {url}", flush=True)
        print(
            f"      log in as staff at {library.url}/staff.html with {STAFF_EMAIL}, "
            f"password {staff_password}",
            flush=True,
        )
        print(f"DEMO_URL {url}", flush=True)
        if args.exit_when_ready:
            return _check_ready(library, url, shown)
        print("serving until Ctrl-C", flush=True)
        while library.server is not None and library.server.poll() is None:
            time.sleep(1)
        print("demo: the service stopped", file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        print("\ndemo: stopping", file=sys.stderr)
        return 0
    except (RuntimeError, TimeoutError, httpx.HTTPError, OSError) as exc:
        print(f"demo: error: {exc} (logs in {library.logs})", file=sys.stderr)
        return 1
    finally:
        library.stop()


def simulate_faces(work: Path, args: argparse.Namespace, pixel_um: float) -> dict[str, Path]:
    """The six faces' bundle ZIPs, simulated ``args.jobs`` at a time in worker processes
    (numpy renders one frame on one core); a line per face as it is done."""
    out: dict[str, Path] = {}
    t0 = time.monotonic()
    with ProcessPoolExecutor(max_workers=args.jobs) as pool:
        futures = {
            pool.submit(
                simulate_face_zip,
                work,
                face,
                seed=args.seed,
                tablet_mm=tuple(args.tablet_mm),
                pixel_um=pixel_um,
            ): face
            for face in DEMO_FACES
        }
        for future in as_completed(futures):
            face = futures[future]
            out[face] = future.result()
            mb = out[face].stat().st_size / 2**20
            print(
                f"      {face}: simulated ({mb:.0f} MB) at {time.monotonic() - t0:.0f} s",
                flush=True,
            )
    return out


def _tablet_mm(text: str) -> tuple[float, float, float]:
    try:
        w, h, t = (float(v) for v in text.lower().split("x"))
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected WxHxT in mm, got {text!r}") from None
    return w, h, t


def _terminate(signum, _frame) -> None:
    raise KeyboardInterrupt  # SIGTERM stops the demo like Ctrl-C (processes cleaned up)


def main(argv: list[str] | None = None) -> int:
    signal.signal(signal.SIGTERM, _terminate)
    parser = argparse.ArgumentParser(
        prog="python -m worker.demo", description=__doc__.splitlines()[0]
    )
    parser.add_argument("--data-dir", default=str(REPO / "var" / "demo"), help="wiped at start")
    parser.add_argument("--port", type=int, default=8000, help="default 8000 (make demo PORT=N)")
    parser.add_argument("--seed", type=int, default=7)
    parser.add_argument(
        "--tablet-mm",
        type=_tablet_mm,
        default=DEMO_TABLET_MM,
        metavar="WxHxT",
        help="the simulated tablet's width, height and thickness in mm (default 14x11x7)",
    )
    parser.add_argument(
        "--pixel-um",
        type=float,
        default=26.8,
        help="pixel size on the tablet in µm (default 26.8, the paper's; each face's frame "
        "follows the tablet; e.g. 400 for a quick CI run)",
    )
    cores = max(1, min(2, os.cpu_count() or 1))
    parser.add_argument(
        "--jobs", type=int, default=cores, help=f"faces simulated at a time (default {cores})"
    )
    parser.add_argument(
        "--concurrency",
        type=int,
        default=cores,
        help=f"reconstructions the worker runs at a time (default {cores})",
    )
    parser.add_argument(
        "--timeout",
        type=float,
        default=1800.0,
        help="seconds to wait for the reconstructions, then for the registration (default "
        "1800: a busy machine can take far longer than the ~5 minutes of a free one)",
    )
    parser.add_argument(
        "--exit-when-ready", action="store_true", help="stop once the models are ready"
    )
    return run_demo(parser.parse_args(argv))


if __name__ == "__main__":
    sys.exit(main())
