"""The real library service on a free port, with seeded tablets and models, and Debian's
chromium driven by Playwright — shared by the browser tests' fixtures and the screenshot
script (``python tests/system/browser/take_screenshots.py``).

Nothing here downloads a browser: Playwright launches ``/usr/bin/chromium`` with SwiftShader
(software WebGL), so the tests run on machines without a GPU.
"""

from __future__ import annotations

import fcntl
import os
import socket
import subprocess
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path

import httpx


def load_sibling(name: str):
    """Import a module of this folder by path (the tests folders are not packages)."""
    import importlib.util

    key = f"hammurabi_browser_{name}"
    if key in sys.modules:
        return sys.modules[key]
    spec = importlib.util.spec_from_file_location(key, Path(__file__).with_name(f"{name}.py"))
    module = importlib.util.module_from_spec(spec)
    sys.modules[key] = module
    spec.loader.exec_module(module)
    return module


_synthetic = load_sibling("synthetic_model")
ModelFacts = _synthetic.ModelFacts
make_model_dir = _synthetic.make_model_dir

REPO = Path(__file__).resolve().parents[3]
FRONTEND = REPO / "frontend"
DIST = FRONTEND / "dist"
CHROMIUM = "/usr/bin/chromium"
CHROMIUM_ARGS = [
    "--use-angle=swiftshader",
    "--enable-unsafe-swiftshader",
    "--no-sandbox",
    "--disable-gpu-sandbox",
    "--disable-background-networking",
    "--disable-component-update",
    "--no-first-run",
]
STAFF_EMAIL = "curator@example.org"
STAFF_PASSWORD = "clay tablets are patient"
UPLOAD_CHUNK_BYTES = 512 * 1024


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _sources_newer_than(stamp: Path) -> bool:
    if not stamp.exists():
        return True
    t = stamp.stat().st_mtime
    watched = [*FRONTEND.glob("*.html"), FRONTEND / "vite.config.js", *FRONTEND.glob("src/**/*")]
    return any(p.stat().st_mtime > t for p in watched if p.is_file())


def ensure_frontend_built() -> Path:
    """Build frontend/dist if it is missing or older than its sources (once, under a lock)."""
    DIST.parent.mkdir(exist_ok=True)
    # the lock lives in node_modules/ (git-ignored), which the build needs anyway
    with open(FRONTEND / "node_modules" / ".build.lock", "w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)
        if _sources_newer_than(DIST / "index.html"):
            subprocess.run(
                ["npm", "run", "--silent", "build"],
                cwd=FRONTEND,
                check=True,
                stdout=subprocess.DEVNULL,
                stderr=subprocess.PIPE,
            )
    return DIST


@dataclass
class Library:
    """A running library service with what the tests seeded into it."""

    url: str
    process: subprocess.Popen
    data_dir: Path
    tablets: dict[str, int] = field(default_factory=dict)  # designation -> id
    models: dict[str, int] = field(default_factory=dict)  # label -> model id
    facts: ModelFacts | None = None
    log: object = None
    env: dict = field(default_factory=dict)

    def stop(self) -> None:
        self.process.terminate()
        try:
            self.process.wait(timeout=10)
        except subprocess.TimeoutExpired:
            self.process.kill()
            self.process.wait()
        if self.log is not None:
            self.log.close()

    def add_tablet_model(self, designation: str, model_dir: Path) -> int:
        """A succeeded registration job of tablet ``designation`` storing ``model_dir`` (a
        whole-tablet model), as the worker stores it; returns the model's id."""
        from backend import jobs
        from backend.db import make_engine, make_sessionmaker, session_scope
        from backend.storage import LocalStorage
        from backend.tables import JobKind

        engine = make_engine(f"sqlite:///{self.data_dir / 'hammurabi.db'}")
        try:
            factory = make_sessionmaker(engine)
            storage = LocalStorage(self.data_dir / "storage")
            with session_scope(factory) as session:
                tablet_id = self.tablets[designation]
                job = jobs.create(session, tablet_id=tablet_id, kind=JobKind.register)
                session.commit()
                jobs.mark_running(session, job_id=job.id)
                model = jobs.mark_succeeded(
                    session, job_id=job.id, model_dir=model_dir, storage=storage
                )
                return model.id
        finally:
            engine.dispose()

    def add_model(self, label: str, designation: str, face: str, model_dir: Path) -> int:
        """A scan of ``face`` of tablet ``designation`` with a succeeded job storing
        ``model_dir`` (a face model, e.g. one with tiles/), stored as the worker stores it;
        recorded under ``label`` and returns the model's id."""
        from backend.db import make_engine, make_sessionmaker
        from backend.storage import LocalStorage

        engine = make_engine(f"sqlite:///{self.data_dir / 'hammurabi.db'}")
        try:
            self.models[label] = _add_model(
                make_sessionmaker(engine),
                LocalStorage(self.data_dir / "storage"),
                tablet_id=self.tablets[designation],
                face=face,
                label=label,
                model_dir=model_dir,
            )
            return self.models[label]
        finally:
            engine.dispose()


TABLETS = [
    dict(
        designation="P999001",
        p_number="P999001",
        museum_no="BM 99001",
        collection="British Museum",
        period="Old Babylonian",
        provenience="Sippar",
        genre="Legal",
        language="Akkadian",
        is_public=True,
    ),
    dict(
        designation="P999002",
        p_number="P999002",
        museum_no="YBC 99002",
        collection="Yale Babylonian Collection",
        period="Ur III",
        provenience="Drehem",
        genre="Administrative",
        language="Sumerian",
        is_public=True,
    ),
    dict(
        designation="P999003",
        p_number="P999003",
        museum_no="VAT 99003",
        collection="Vorderasiatisches Museum",
        period="Old Babylonian",
        provenience="Nippur",
        genre="Literary",
        language="Sumerian",
        is_public=True,
    ),
]


def _add_model(factory, storage, *, tablet_id: int, face: str, label: str, model_dir: Path) -> int:
    """A scan with a succeeded job whose model is ``model_dir``, stored like the worker does."""
    from backend import jobs
    from backend.db import session_scope
    from backend.tables import Scan

    with session_scope(factory) as session:
        scan = Scan(
            tablet_id=tablet_id,
            face=face,
            bundle_key=f"fixtures/{label}",
            bundle_sha256="0" * 64,
            size_bytes=0,
            manifest={},
        )
        session.add(scan)
        session.flush()
        job = jobs.create(session, scan=scan)
        session.commit()
        jobs.mark_running(session, job_id=job.id)
        model = jobs.mark_succeeded(session, job_id=job.id, model_dir=model_dir, storage=storage)
        return model.id


def _migrate(data_dir: Path) -> str:
    from backend.db import migrate

    url = f"sqlite:///{data_dir / 'hammurabi.db'}"
    migrate(url)
    return url


def _seed(
    url: str, data_dir: Path, work: Path, extra_models: list[tuple[str, str, str, Path]]
) -> tuple[dict, dict, ModelFacts]:
    """Add an institution, a staff user, three tablets and two model versions of the first
    tablet's obverse (made through the job functions the worker uses, so they are stored
    exactly like real models) to the migrated database at ``url``."""
    from backend import crud
    from backend.db import make_engine, make_sessionmaker, session_scope
    from backend.storage import LocalStorage
    from backend.tables import Role

    engine = make_engine(url)
    factory = make_sessionmaker(engine)
    storage = LocalStorage(data_dir / "storage")
    tablets: dict[str, int] = {}
    models: dict[str, int] = {}
    facts = make_model_dir(work / "model_v1", seed=1)
    make_model_dir(work / "model_v2", seed=2, tint=0.08)
    with session_scope(factory) as session:
        inst = crud.get_or_create_institution(session, name="Test Museum")
        crud.create_user(
            session,
            email=STAFF_EMAIL,
            role=Role.staff,
            password=STAFF_PASSWORD,
            institution_id=inst.id,
        )
        for fields in TABLETS:
            t = crud.create_tablet(session, fields=dict(fields), institution_id=inst.id)
            tablets[t.designation] = t.id
    first = tablets[TABLETS[0]["designation"]]
    for label in ("v1", "v2"):
        models[label] = _add_model(
            factory,
            storage,
            tablet_id=first,
            face="obverse",
            label=label,
            model_dir=work / f"model_{label}",
        )
    for label, designation, face, model_dir in extra_models:
        models[label] = _add_model(
            factory,
            storage,
            tablet_id=tablets[designation],
            face=face,
            label=label,
            model_dir=model_dir,
        )
    engine.dispose()
    return tablets, models, facts


def start_library(tmp: Path, *, extra_models: list | None = None) -> Library:
    """Seed a data directory under ``tmp`` and serve it (API + built frontend).

    ``extra_models``: (label, tablet designation, face, model directory) to add, e.g. a real
    reconstruction for the documentation's screenshots."""
    dist = ensure_frontend_built()
    data_dir = tmp / "data"
    data_dir.mkdir(parents=True)
    db_url = _migrate(data_dir)
    port = free_port()
    env = {
        **os.environ,
        "HAMMURABI_ENVIRONMENT": "test",
        "HAMMURABI_DATA_DIR": str(data_dir),
        "HAMMURABI_FRONTEND_DIST": str(dist),
        "HAMMURABI_SECRET_KEY": "browser-tests-" + "k" * 40,
        # small chunks, so that a test bundle of a few MB is a resumable multi-chunk upload
        "HAMMURABI_UPLOAD_CHUNK_SIZE_BYTES": str(UPLOAD_CHUNK_BYTES),
    }
    # No HAMMURABI_BROKER_URL: the embedded broker (a SQLite file in the data dir), so that
    # start_worker() can run real reconstruction workers without any server.
    env.pop("HAMMURABI_BROKER_URL", None)
    log = open(tmp / "server.log", "wb")  # noqa: SIM115 - lives as long as the server
    process = subprocess.Popen(
        [
            sys.executable,
            "-m",
            "uvicorn",
            "backend.main:create_app",
            "--factory",
            "--host",
            "127.0.0.1",
            "--port",
            str(port),
            "--log-level",
            "warning",
        ],
        cwd=REPO,
        env=env,
        stdout=log,
        stderr=subprocess.STDOUT,
    )
    url = f"http://127.0.0.1:{port}"
    try:
        # seeded while the server starts: both take seconds on a busy machine
        tablets, models, facts = _seed(db_url, data_dir, tmp, extra_models or [])
    except BaseException:
        process.kill()
        process.wait()
        log.close()
        raise
    deadline = time.monotonic() + 60
    while True:
        try:
            if httpx.get(f"{url}/api/v1/health", timeout=1).status_code == 200:
                break
        except httpx.HTTPError:
            pass
        if process.poll() is not None or time.monotonic() > deadline:
            process.kill()
            process.wait()
            log.close()
            raise RuntimeError(
                f"the library service did not start: {(tmp / 'server.log').read_text()[-2000:]}"
            )
        time.sleep(0.2)
    return Library(
        url=url,
        process=process,
        data_dir=data_dir,
        tablets=tablets,
        models=models,
        facts=facts,
        log=log,
        env=env,
    )


def start_worker(library: Library, log_path: Path) -> subprocess.Popen:
    """A real reconstruction worker (``hammurabi worker``) on the library's embedded broker."""
    log = open(log_path, "wb")  # noqa: SIM115 - closed by stop_worker
    process = subprocess.Popen(
        [
            sys.executable,
            "-m",
            "backend.cli",
            "worker",
            "--concurrency",
            "1",
            "--log-level",
            "warning",
        ],
        cwd=REPO,
        env=library.env,
        stdout=log,
        stderr=subprocess.STDOUT,
    )
    process.log_file = log
    return process


def stop_worker(process: subprocess.Popen) -> None:
    process.terminate()
    try:
        process.wait(timeout=20)
    except subprocess.TimeoutExpired:
        process.kill()
        process.wait()
    process.log_file.close()


def launch_chromium(playwright):
    return playwright.chromium.launch(executable_path=CHROMIUM, args=CHROMIUM_ARGS)


_SETTLE_JS = """async () => {
  const v = window.hammurabi.viewer;
  await v.whenIdle?.();
  const frame = () => new Promise(r => requestAnimationFrame(() => requestAnimationFrame(r)));
  const deadline = performance.now() + 60000;
  let calm = 0;
  while (calm < 2) {
    v.invalidate();
    await frame();
    const s = v.streaming();
    calm = !s || s.idle ? calm + 1 : 0;
    if (performance.now() > deadline) throw new Error('tiles still loading after 60 s');
    if (!calm) await new Promise(r => setTimeout(r, 50));
  }
  return v.streaming();
}"""


def settle_tiles(page) -> dict | None:
    """Wait for idle maps and, for a streamed model, until after a drawn frame (which runs
    the renderer's update) no tile is queued, downloading or parsing, twice in a row; the
    viewer's streaming figures then (None for a single-mesh model)."""
    return page.evaluate(_SETTLE_JS)


def cut_section(page, half_width_px: float):
    """Draw a section straight across the viewer's middle row, from half_width_px left of
    its centre to as far right (the section tool's key, then two clicks); returns the
    section panel once it is shown."""
    box = page.locator("#viewer").bounding_box()
    x, y = box["x"] + box["width"] / 2, box["y"] + box["height"] / 2
    page.locator("#viewer").focus()
    page.keyboard.press("x")
    page.mouse.click(x - half_width_px, y)
    page.mouse.click(x + half_width_px, y)
    panel = page.locator("#section-panel")
    panel.wait_for(state="visible")
    return panel
