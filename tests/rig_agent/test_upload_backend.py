"""Upload to the real library service in a subprocess, killed with SIGKILL half way."""

from __future__ import annotations

import os
import signal
import socket
import subprocess
import sys
import threading
import time
from pathlib import Path

import httpx
import numpy as np
import pytest

from rig_agent.assemble import write_scan_bundle
from rig_agent.patterns import ProjectorGeometry
from rig_agent.plan import expand, quick_plan
from rig_agent.spool import Spool
from rig_agent.upload import LibraryClient, sha256_file, upload_scan

SERVER = Path(__file__).with_name("real_library.py")
REPO = Path(__file__).resolve().parents[2]
CHUNK = 32 * 1024
GEOMETRY = ProjectorGeometry(width=64, height=48, pixel_size_um=200.0)
CAMERA = {"width": 64, "height": 48, "pixel_size_um": 100.0, "bit_depth": 12}


def free_port() -> int:
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return sock.getsockname()[1]


class RealLibrary:
    def __init__(self, data: Path) -> None:
        self.data, self.port, self.process = data, free_port(), None
        self.restarts: list[threading.Timer] = []

    def restart_later(self, delay_s: float) -> None:
        timer = threading.Timer(delay_s, self.start, kwargs={"wait": False})
        self.restarts.append(timer)
        timer.start()

    @property
    def url(self) -> str:
        return f"http://127.0.0.1:{self.port}"

    def start(self, *, wait: bool = True) -> None:
        self.process = subprocess.Popen(
            [
                sys.executable,
                str(SERVER),
                "--port",
                str(self.port),
                "--data",
                str(self.data),
                "--chunk-size",
                str(CHUNK),
            ],
            env={**os.environ, "PYTHONPATH": str(REPO)},
        )
        if wait:
            self.wait_ready()

    def wait_ready(self, timeout_s: float = 120.0) -> None:
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            assert self.process.poll() is None, "the library service exited"
            try:
                if httpx.get(self.url + "/api/v1/tablets", timeout=2).status_code == 200:
                    return
            except httpx.TransportError:
                pass
            time.sleep(0.2)
        raise AssertionError("the library service did not start")

    def kill(self) -> None:
        os.kill(self.process.pid, signal.SIGKILL)
        self.process.wait()

    @property
    def token(self) -> str:
        return (self.data / "token.txt").read_text()

    @property
    def tablet_id(self) -> int:
        return int((self.data / "tablet_id.txt").read_text())


@pytest.fixture
def library(tmp_path):
    server = RealLibrary(tmp_path / "library")
    server.start()
    yield server
    for timer in server.restarts:
        timer.join()  # never leave a server started after the test is over
    if server.process.poll() is None:
        server.kill()


def spooled(spool, kind, seed):
    target = "reference" if kind == "calibration" else "object"
    meta = {
        "face": "obverse" if kind == "scan" else None,
        "tablet": {"designation": "P123456"},
        "camera": CAMERA,
        "polar_deg": 45.0,
        "reference_reflectance": 0.95,
    }
    scan = spool.create(kind=kind, shots=expand(quick_plan(), GEOMETRY, target=target), meta=meta)
    rng = np.random.default_rng(seed)
    for shot in scan.shots:
        scan.save_frame(shot, rng.integers(200, 3000, size=(48, 64), dtype=np.uint16))
    return scan


@pytest.mark.slow
def test_upload_to_the_library_survives_kill_9_and_is_idempotent(library, tmp_path):
    spool = Spool(tmp_path / "spool")
    scan = spooled(spool, "scan", 1)
    bundle = write_scan_bundle(scan, spooled(spool, "calibration", 2))
    size = bundle.stat().st_size
    assert size > 8 * CHUNK  # several chunks before and after the kill
    calls = []

    def progress(done: int, total: int) -> None:
        calls.append(done)
        if len(calls) == 4:  # three chunks confirmed: kill -9, restart a moment later
            library.kill()
            library.restart_later(0.3)

    client = LibraryClient(library.url, library.token, retries=14, backoff_s=0.05, timeout_s=30)
    try:
        tablet_id = client.find_tablet("P123456")
        assert tablet_id == library.tablet_id
        result = upload_scan(scan, client, tablet_id=tablet_id, progress=progress)
        assert calls[-1] == size
        upload_id = scan.state["upload"]["id"]
        state = client.request("GET", f"/uploads/{upload_id}").json()
        assert state["state"] == "complete" and state["size_bytes"] == size
        # The library verified our SHA-256 of the whole file before making the scan.
        assert scan.state["upload"]["confirmed_sha256"] == sha256_file(bundle)
        assert result["scan"]["tablet_id"] == tablet_id and result["job"]["id"]
        # The same scan again (a new upload of the same bundle) is the same library scan.
        scan.update_state(upload=None, phase="bundled")
        again = upload_scan(scan, client, tablet_id=tablet_id)
        assert again["scan"]["id"] == result["scan"]["id"]
    finally:
        client.close()
