"""Fixtures of the rig agent tests: a fake library server in a subprocess."""

from __future__ import annotations

import hashlib
import os
import signal
import socket
import subprocess
import sys
from pathlib import Path

import pytest

FAKE = Path(__file__).with_name("fake_library.py")
TOKEN = "rig-test-token"
CHUNK = 64 * 1024


def free_port() -> int:
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return sock.getsockname()[1]


class FakeLibrary:
    def __init__(self, data: Path) -> None:
        self.data, self.port, self.process = data, free_port(), None

    @property
    def url(self) -> str:
        return f"http://127.0.0.1:{self.port}"

    def start(self) -> None:
        self.process = subprocess.Popen(
            [
                sys.executable,
                str(FAKE),
                "--port",
                str(self.port),
                "--data",
                str(self.data),
                "--token",
                TOKEN,
                "--chunk-size",
                str(CHUNK),
            ],
            stdout=subprocess.PIPE,
            text=True,
        )
        assert self.process.stdout.readline().strip() == "ready"

    def kill(self) -> None:
        os.kill(self.process.pid, signal.SIGKILL)
        self.process.wait()
        self.process.stdout.close()

    def received_bytes(self) -> int:
        log = self.data / "received.log"
        return sum(int(line.split()[1]) for line in log.read_text().splitlines())

    def stored_sha256(self) -> str:
        (part,) = self.data.glob("*.part")
        return hashlib.sha256(part.read_bytes()).hexdigest()


@pytest.fixture
def library(tmp_path):
    """The fake library (token TOKEN, 64 KiB chunks, tablet P123456 has id 7), running."""
    server = FakeLibrary(tmp_path / "library")
    server.start()
    yield server
    if server.process.poll() is None:
        server.kill()
