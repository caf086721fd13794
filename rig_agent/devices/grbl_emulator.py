"""A GRBL 1.1 controller emulated on a real pseudo-terminal.

The emulator opens a pty pair (``os.openpty``) and answers on the master side from a
thread, as GRBL 1.1 does on its serial port: ``ok``/``error:N`` per line, ``?`` status
reports at any time, ``0x18`` soft reset with the welcome line, homing (``$H``),
unlock (``$X``), build info (``$I``), ``G0``/``G1`` moves in ``G90``/``G91`` that take
time (``<Run|…>`` until they end), soft-limit alarms for targets outside the travel,
and hard-limit alarms on demand. Drivers open :attr:`GrblEmulator.port` with
``serial.serial_for_url`` — the same code path as a USB controller.
"""

from __future__ import annotations

import os
import re
import select
import threading
import time
import tty
from dataclasses import dataclass, field

WELCOME = "Grbl 1.1h ['$' for help]"
_NUMBER = re.compile(r"[-+]?(?:\d+\.?\d*|\.\d+)")
_MOTION = {0: "motion", 1: "motion", 90: "distance", 91: "distance", 20: "units", 21: "units"}
_AXES = "XYZ"
LINE_MAX = 80  # GRBL's LINE_BUFFER_SIZE


@dataclass
class _Move:
    start: tuple[float, float, float]
    target: tuple[float, float, float]
    duration_s: float
    started: float = 0.0
    number: int = 0


@dataclass
class EmulatorConfig:
    """Machine settings: travel per axis (machine coordinates after homing) and rates."""

    travel: dict[str, tuple[float, float]] = field(
        default_factory=lambda: {"X": (0.0, 360.0), "Y": (0.0, 100.0), "Z": (0.0, 50.0)}
    )
    rapid_rate_per_s: float = 3600.0  # units (deg or mm) per second for G0
    homing_enabled: bool = True
    homing_time_s: float = 0.02
    soft_limits: bool = True


class GrblEmulator:
    """GRBL 1.1 on a pseudo-terminal; use as a context manager or call start()/stop()."""

    def __init__(self, config: EmulatorConfig | None = None) -> None:
        self.config = config or EmulatorConfig()
        self.received: list[str] = []  # every line received, normalised as GRBL sees it
        # trip ALARM:1 half way through move N (counted since the last reset), once
        self.hard_limit_on_move: int | None = None
        self._lock = threading.Lock()
        self._master = -1
        self._slave = -1
        self.port = ""
        self._thread: threading.Thread | None = None
        self._stop = threading.Event()
        self._power_on()

    # -- lifecycle ----------------------------------------------------------------------
    def _power_on(self) -> None:
        self.position = (0.0, 0.0, 0.0)
        self.state = "Alarm" if self.config.homing_enabled else "Idle"
        self._locked = self.config.homing_enabled
        self._critical = False
        self._line = bytearray()
        self._moves: list[_Move] = []
        self._homing_until: float | None = None
        self._absolute = True
        self._motion_mode = 0
        self._feed_per_min: float | None = None
        self._move_count = 0

    def start(self) -> GrblEmulator:
        self._master, self._slave = os.openpty()
        tty.setraw(self._slave)  # no echo, no line discipline: bytes as on a UART
        self.port = os.ttyname(self._slave)
        self._stop.clear()
        self._thread = threading.Thread(target=self._run, name="grbl-emulator", daemon=True)
        self._thread.start()
        self._emit("", WELCOME)
        if self._locked:
            self._emit("[MSG:'$H'|'$X' to unlock]")
        return self

    def stop(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=2)
            self._thread = None
        for fd in (self._master, self._slave):
            if fd >= 0:
                os.close(fd)
        self._master = self._slave = -1

    def __enter__(self) -> GrblEmulator:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()

    # -- I/O ----------------------------------------------------------------------------
    def _emit(self, *lines: str) -> None:
        data = "".join(f"{line}\r\n" for line in lines).encode("ascii")
        if self._master >= 0:
            os.write(self._master, data)

    def _run(self) -> None:
        while not self._stop.is_set():
            ready, _, _ = select.select([self._master], [], [], 0.002)
            with self._lock:
                self._advance(time.monotonic())
                if not ready:
                    continue
                try:
                    data = os.read(self._master, 4096)
                except OSError:
                    continue
                for byte in data:
                    self._on_byte(byte)

    def _on_byte(self, byte: int) -> None:
        if byte == ord("?"):
            self._emit(self.status_report())
        elif byte == 0x18:
            self._soft_reset()
        elif byte == ord("!"):
            if self.state == "Run":
                self.state = "Hold:0"
        elif byte == ord("~"):
            if self.state.startswith("Hold"):
                self.state = "Run"
        elif byte in (ord("\n"), ord("\r")):
            raw, self._line = bytes(self._line), bytearray()
            if not self._critical:
                self._on_line(raw.decode("ascii", errors="replace"))
        elif not self._critical:
            self._line.append(byte)

    # -- state ------------------------------------------------------------------------
    def status_report(self) -> str:
        x, y, z = self.position
        state = "Idle" if self.state == "Idle" else self.state
        return f"<{state}|MPos:{x:.3f},{y:.3f},{z:.3f}|FS:0,0>"

    def _alarm(self, code: int) -> None:
        self._moves.clear()
        self._homing_until = None
        self.state = "Alarm"
        self._locked = True
        self._emit(f"ALARM:{code}")
        if code in (1, 2):  # critical events: GRBL waits for a reset
            self._critical = True
            self._emit("[MSG:Reset to continue]")

    def _soft_reset(self) -> None:
        if self._moves or self._homing_until is not None:
            self._alarm(3)
        locked = self._locked
        position = self.position
        self._power_on()
        self.position = position
        self._locked = locked
        self.state = "Alarm" if locked else "Idle"
        self._emit("", WELCOME)
        if locked:
            self._emit("[MSG:'$H'|'$X' to unlock]")

    def _advance(self, now: float) -> None:
        if self._homing_until is not None and now >= self._homing_until:
            self._homing_until = None
            self.position = (0.0, 0.0, 0.0)
            self.state = "Idle"
            self._locked = False
            self._emit("ok")  # GRBL acknowledges $H when the cycle has finished
        if self.state.startswith("Hold") or not self._moves:
            return
        move = self._moves[0]
        if move.started == 0.0:
            move.started = now
        fraction = 1.0 if move.duration_s <= 0 else min(1.0, (now - move.started) / move.duration_s)
        if self.hard_limit_on_move == move.number and fraction >= 0.5:
            self.hard_limit_on_move = None  # one switch hit, not one per power cycle
            fraction = 0.5
            self.position = _lerp(move.start, move.target, fraction)
            self._alarm(1)
            return
        self.position = _lerp(move.start, move.target, fraction)
        if fraction >= 1.0:
            self._moves.pop(0)
            if not self._moves:
                self.state = "Idle"

    # -- commands -----------------------------------------------------------------------
    def _on_line(self, raw: str) -> None:
        line = _normalise(raw)
        if len(raw) > LINE_MAX:
            self._emit("error:11")
            return
        self.received.append(line)
        if not line:
            self._emit("ok")
        elif line.startswith("$"):
            self._system(line)
        elif self._locked:
            self._emit("error:9")
        else:
            code = self._gcode(line)
            if code >= 0:  # a soft-limit alarm (-1) leaves the line unanswered until reset
                self._emit("ok" if code == 0 else f"error:{code}")

    def _system(self, line: str) -> None:
        busy = bool(self._moves) or self._homing_until is not None
        if line == "$H":
            if not self.config.homing_enabled:
                self._emit("error:5")
            elif busy:
                self._emit("error:8")
            else:
                self.state = "Home"
                self._homing_until = time.monotonic() + self.config.homing_time_s
        elif line == "$X":
            if self._locked:
                self._emit("[MSG:Caution: Unlocked]")
            self._locked = False
            self.state = "Idle"
            self._emit("ok")
        elif line == "$I":
            self._emit("[VER:1.1h.20190830:]", "[OPT:V,15,128]", "ok")
        elif line == "$$":
            x, y, z = (self.config.travel[a][1] for a in _AXES)
            lines = [
                f"$20={int(self.config.soft_limits)}",
                f"$22={int(self.config.homing_enabled)}",
            ]
            lines += [f"$130={x:.3f}", f"$131={y:.3f}", f"$132={z:.3f}"]
            self._emit(*lines, "ok")
        else:
            self._emit("error:3")

    def _gcode(self, line: str) -> int:
        """Execute one block; return 0 or the GRBL error code."""
        words: dict[str, float] = {}
        groups: dict[str, int] = {}
        non_modal: list[int] = []
        i = 0
        while i < len(line):
            letter = line[i]
            if not letter.isalpha():
                return 1
            number = _NUMBER.match(line, i + 1)
            if number is None:
                return 2
            value = float(number.group())
            i = number.end()
            if letter == "G":
                if value != int(value):
                    return 20
                g = int(value)
                if g == 4:
                    non_modal.append(g)
                    continue
                if g not in _MOTION:
                    return 20
                if _MOTION[g] in groups:
                    return 21
                groups[_MOTION[g]] = g
            elif letter in "XYZFPN":
                if letter in words:
                    return 25
                words[letter] = value
            else:
                return 20
        if "F" in words:
            if words["F"] < 0:
                return 4
            self._feed_per_min = words["F"]
        if "distance" in groups:
            self._absolute = groups["distance"] == 90
        if "motion" in groups:
            self._motion_mode = groups["motion"]
        if 4 in non_modal:
            if "P" not in words:
                return 28
            return 0
        axis_words = {a: words[a] for a in _AXES if a in words}
        if not axis_words:
            return 0
        if self._motion_mode == 1 and not self._feed_per_min:
            return 22
        return self._queue_move(axis_words)

    def _queue_move(self, axis_words: dict[str, float]) -> int:
        start = self._moves[-1].target if self._moves else self.position
        target = tuple(
            axis_words.get(a, start[k]) if self._absolute else start[k] + axis_words.get(a, 0.0)
            for k, a in enumerate(_AXES)
        )
        if self.config.soft_limits:
            for k, axis in enumerate(_AXES):
                low, high = self.config.travel[axis]
                if not low - 1e-9 <= target[k] <= high + 1e-9:
                    self._alarm(2)
                    return -1
        rate = (
            self.config.rapid_rate_per_s
            if self._motion_mode == 0
            else (self._feed_per_min or 1.0) / 60.0
        )
        distance = max(abs(t - s) for t, s in zip(target, start, strict=True))
        self._move_count += 1
        self._moves.append(
            _Move(start=start, target=target, duration_s=distance / rate, number=self._move_count)
        )
        self.state = "Run"
        return 0


def _lerp(a: tuple[float, ...], b: tuple[float, ...], t: float) -> tuple[float, float, float]:
    x, y, z = (p + (q - p) * t for p, q in zip(a, b, strict=True))
    return (x, y, z)


def _normalise(raw: str) -> str:
    """As GRBL's line reader: drop spaces, comments in () or after ';', upper-case."""
    out: list[str] = []
    in_paren = False
    for ch in raw:
        if in_paren:
            in_paren = ch != ")"
        elif ch == "(":
            in_paren = True
        elif ch == ";":
            break
        elif not ch.isspace():
            out.append(ch.upper())
    return "".join(out)
