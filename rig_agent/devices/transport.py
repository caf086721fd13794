"""A line-oriented serial link opened by URL (after pymeasure's adapters).

Drivers never open ports themselves: they receive a :class:`SerialLink`, which
opens its connection with ``serial.serial_for_url(url, timeout=…)``. The same
driver therefore runs on a USB port (``/dev/ttyACM0``), on the GRBL emulator's
pseudo-terminal, on pyserial's ``loop://`` and ``spy://`` handlers, or on a
scripted fake connection given as ``opener`` in tests.
"""

from __future__ import annotations

import contextlib
import time
from collections.abc import Callable
from typing import Any

import serial

from rig_agent.devices.base import DeviceError, DeviceTimeout

Opener = Callable[..., Any]

#: Errors that mean the cable was pulled or the USB device re-enumerated.
LINK_ERRORS: tuple[type[BaseException], ...] = (serial.SerialException, OSError)


class LinkLost(DeviceError):
    """The serial connection broke and could not be reopened."""


class SerialLink:
    """Reads and writes lines on a connection opened by URL, and reopens it after a drop.

    ``timeout_s`` is the read timeout handed to the connection (the granularity of waits);
    callers give their own deadlines to :meth:`read_line`.
    """

    def __init__(
        self,
        url: str,
        *,
        timeout_s: float = 0.05,
        opener: Opener = serial.serial_for_url,
        baudrate: int = 115200,
    ) -> None:
        if not isinstance(url, str) or not url:
            raise ValueError(f"url must be a non-empty string, got {url!r}")
        if timeout_s <= 0:
            raise ValueError(f"timeout_s must be > 0, got {timeout_s!r}")
        self.url = url
        self.timeout_s = timeout_s
        self.baudrate = baudrate
        self._opener = opener
        self._connection: Any = None
        self._buffer = bytearray()

    @property
    def is_open(self) -> bool:
        return self._connection is not None

    def open(self) -> None:
        """Open the connection; a missing port becomes a :class:`LinkLost` naming the URL."""
        if self._connection is not None:
            return
        try:
            self._connection = self._opener(
                self.url, timeout=self.timeout_s, baudrate=self.baudrate
            )
        except LINK_ERRORS as exc:
            raise LinkLost(
                f"cannot open the motion controller at {self.url!r} ({exc}). "
                "Check the USB cable and the `stage_url` setting."
            ) from exc
        self._buffer.clear()

    def close(self) -> None:
        connection, self._connection = self._connection, None
        self._buffer.clear()
        if connection is not None:
            # Already gone: closing a dead port must not mask the original error.
            with contextlib.suppress(*LINK_ERRORS):
                connection.close()

    def reopen(self, *, within_s: float, interval_s: float = 0.2) -> None:
        """Close and reopen by URL, retrying until ``within_s`` seconds have passed.

        A USB serial adapter disappears for a moment when it is unplugged or resets; the
        device node comes back under the same name (or the same by-id link).
        """
        self.close()
        deadline = time.monotonic() + within_s
        while True:
            try:
                self.open()
                return
            except LinkLost:
                if time.monotonic() >= deadline:
                    raise
                time.sleep(interval_s)

    def _require(self) -> Any:
        if self._connection is None:
            raise LinkLost(f"the connection to {self.url!r} is not open")
        return self._connection

    def write(self, data: bytes) -> None:
        """Write raw bytes (a line with its newline, or a real-time command byte)."""
        connection = self._require()
        connection.write(data)
        connection.flush()

    def write_line(self, line: str) -> None:
        self.write(line.encode("ascii") + b"\n")

    def discard_input(self) -> None:
        """Drop whatever was received but not read (stale replies after a reconnect)."""
        connection = self._require()
        connection.reset_input_buffer()
        self._buffer.clear()

    def read_line(self, *, timeout_s: float) -> str:
        """The next non-empty line without its line ending; :class:`DeviceTimeout` if none."""
        connection = self._require()
        deadline = time.monotonic() + timeout_s
        while True:
            newline = self._buffer.find(b"\n")
            if newline >= 0:
                raw = bytes(self._buffer[:newline])
                del self._buffer[: newline + 1]
                line = raw.decode("ascii", errors="replace").strip()
                if line:
                    return line
                continue
            if time.monotonic() >= deadline:
                raise DeviceTimeout(
                    f"the motion controller at {self.url!r} did not answer within {timeout_s:g} s"
                )
            chunk = connection.read(max(1, connection.in_waiting or 1))
            if chunk:
                self._buffer.extend(chunk)
