"""A scripted serial connection: each expected write is answered by canned bytes."""

from __future__ import annotations

import time

import pytest
import serial

from rig_agent.devices.stage import GrblStage
from rig_agent.devices.transport import SerialLink


class ScriptedConnection:
    """Stands in for ``serial.Serial``; fails loudly on any write the script does not expect.

    ``script`` is a list of ``(expected_write, reply)`` pairs taken from the GRBL 1.1
    interface documentation; ``fail_on`` makes the write of that payload raise
    ``SerialException`` (a USB drop).
    """

    def __init__(
        self,
        script: list[tuple[bytes, bytes]],
        *,
        timeout: float = 0.01,
        fail_on: bytes | None = None,
    ):
        self.script = list(script)
        self.timeout = timeout
        self.fail_on = fail_on
        self.written: list[bytes] = []
        self._out = bytearray()
        self.closed = False

    @property
    def in_waiting(self) -> int:
        return len(self._out)

    def write(self, data: bytes) -> int:
        if self.fail_on is not None and data == self.fail_on:
            raise serial.SerialException("device reports readiness to read but returned no data")
        self.written.append(data)
        if not self.script:
            raise AssertionError(f"unexpected write {data!r}: the script is finished")
        expected, reply = self.script.pop(0)
        if data != expected:
            raise AssertionError(f"expected write {expected!r}, got {data!r}")
        self._out.extend(reply)
        return len(data)

    def read(self, size: int = 1) -> bytes:
        if not self._out:
            time.sleep(self.timeout)
            return b""
        chunk = bytes(self._out[:size])
        del self._out[:size]
        return chunk

    def flush(self) -> None:
        pass

    def reset_input_buffer(self) -> None:
        self._out.clear()

    def close(self) -> None:
        self.closed = True


def opener_for(*connections: ScriptedConnection):
    """An ``opener`` handing out the given connections in turn, recording the URLs asked for."""
    pending = list(connections)
    urls: list[str] = []

    def opener(url: str, **kwargs: object) -> ScriptedConnection:
        urls.append(url)
        if not pending:
            raise serial.SerialException(f"could not open port {url}")
        return pending.pop(0)

    opener.urls = urls  # type: ignore[attr-defined]
    return opener


@pytest.fixture
def scripted():
    """Build a GrblStage on scripted connections: ``scripted(conn1, conn2, ...)``."""

    def build(*connections: ScriptedConnection, **stage_options: object):
        opener = opener_for(*connections)
        link = SerialLink("/dev/ttyFAKE0", opener=opener, timeout_s=0.01)
        options = {"command_timeout_s": 0.3, "poll_interval_s": 0.0, "reconnect_timeout_s": 0.2}
        options.update(stage_options)
        stage = GrblStage(link, **options)
        link.open()
        return stage, opener

    return build


@pytest.fixture
def connection():
    return ScriptedConnection
