"""Driver for a GRBL 1.1 motion controller: light azimuth axis and tablet elevation stage.

Protocol (GRBL 1.1 interface documentation): a line of G-code or a ``$`` command is
answered by ``ok`` or ``error:N``; ``?`` (no newline) is answered at once by a status
report ``<State|MPos:x,y,z|…>``; ``0x18`` is a soft reset, answered by the welcome
line ``Grbl 1.1x ['$' for help]``; alarms are pushed as ``ALARM:N``; after a reset
with homing enabled the controller starts locked in ``Alarm`` and asks for ``$H``
or ``$X`` (``[MSG:'$H'|'$X' to unlock]``).

The azimuth axis is driven in degrees (its steps/unit setting is steps per degree).
"""

from __future__ import annotations

import re
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import TypeVar

from rig_agent.devices.base import DeviceError, DeviceTimeout, Stage, StagePosition
from rig_agent.devices.grbl_codes import describe_alarm, describe_error
from rig_agent.devices.transport import LINK_ERRORS, LinkLost, SerialLink

SOFT_RESET = b"\x18"
STATUS_QUERY = b"?"
_STATUS = re.compile(r"^<(?P<state>[A-Za-z]+)(?::\d+)?\|(?P<fields>.*)>$")
_AXES = "XYZ"
T = TypeVar("T")


class GrblError(DeviceError):
    """The controller rejected a command with ``error:N``."""

    def __init__(self, code: int, command: str) -> None:
        self.code = code
        self.command = command
        super().__init__(
            f"the motion controller rejected {command!r}: {describe_error(code)} (error:{code})"
        )


class GrblAlarm(DeviceError):
    """The controller raised ``ALARM:N``; motion stopped and the controller is locked."""

    def __init__(self, code: int) -> None:
        self.code = code
        super().__init__(f"the motion controller stopped: {describe_alarm(code)} (ALARM:{code})")


@dataclass(frozen=True)
class GrblStatus:
    """A parsed status report: machine state and machine position per axis letter."""

    state: str
    mpos: dict[str, float]
    raw: str


def parse_status(line: str) -> GrblStatus:
    """Parse ``<Idle|MPos:1.000,2.000,3.000|FS:0,0>``; ValueError if ``line`` is not one."""
    match = _STATUS.match(line)
    if match is None:
        raise ValueError(f"line is not a GRBL status report: {line!r}")
    mpos: dict[str, float] = {}
    for field in match["fields"].split("|"):
        name, _, value = field.partition(":")
        if name in ("MPos", "WPos"):
            numbers = [float(v) for v in value.split(",")]
            mpos = dict(zip(_AXES, numbers, strict=False))
    return GrblStatus(state=match["state"], mpos=mpos, raw=line)


class GrblStage(Stage):
    """The scanner's two axes on a GRBL 1.1 controller reached through a :class:`SerialLink`."""

    def __init__(
        self,
        link: SerialLink,
        *,
        azimuth_axis: str = "X",
        elevation_axis: str = "Z",
        command_timeout_s: float = 2.0,
        motion_timeout_s: float = 120.0,
        homing_timeout_s: float = 120.0,
        poll_interval_s: float = 0.05,
        reconnect_timeout_s: float = 10.0,
    ) -> None:
        for name, axis in (("azimuth_axis", azimuth_axis), ("elevation_axis", elevation_axis)):
            if axis not in _AXES:
                raise ValueError(f"{name} must be one of X, Y, Z, got {axis!r}")
        if azimuth_axis == elevation_axis:
            raise ValueError("azimuth_axis and elevation_axis must differ")
        self.link = link
        self.azimuth_axis = azimuth_axis
        self.elevation_axis = elevation_axis
        self.command_timeout_s = command_timeout_s
        self.motion_timeout_s = motion_timeout_s
        self.homing_timeout_s = homing_timeout_s
        self.poll_interval_s = poll_interval_s
        self.reconnect_timeout_s = reconnect_timeout_s
        self.messages: list[str] = []  # [MSG:…] and other push lines, for the log
        self._locked = True

    # -- connection -------------------------------------------------------------------
    def connect(self) -> None:
        """Open the port, soft-reset and wait for the welcome line."""
        self.link.open()
        self.soft_reset()

    def close(self) -> None:
        self.link.close()

    def soft_reset(self) -> None:
        """Send 0x18 and wait for ``Grbl 1.1…``; pending alarms are cleared by the reset."""
        self.link.discard_input()
        self.link.write(SOFT_RESET)
        deadline = time.monotonic() + self.command_timeout_s
        while True:
            line = self.link.read_line(timeout_s=max(0.0, deadline - time.monotonic()))
            if line.startswith("Grbl "):
                break
            self._note(line, raise_alarm=False)
        self._locked = False
        # With homing enabled GRBL boots locked; its unlock hint follows the welcome line.
        status = self.status()
        self._locked = status.state == "Alarm"

    def _reconnect(self, *, allow_locked: bool) -> None:
        self.link.reopen(within_s=self.reconnect_timeout_s)
        self.link.discard_input()
        status = self._status()  # re-sync: the first complete status report after reopening
        if status.state == "Alarm" and allow_locked:
            self._locked = True
        elif status.state == "Alarm":
            # The board reset when the port re-enumerated: its position is gone.
            self._locked = True
            raise DeviceError(
                "the motion controller restarted after its USB connection dropped and lost its "
                "position; check the cable, then run `rig-agent resume` (it re-homes)"
            )

    def _with_reconnect(self, action: Callable[[], T], *, allow_locked: bool = False) -> T:
        """Run ``action``; after a USB drop reopen by URL, re-sync and run it once more.

        A board that reset while the port was away comes back locked in ``Alarm``: only
        ``allow_locked`` actions (homing, unlocking) may then go on.
        """
        try:
            return action()
        except LINK_ERRORS:
            pass
        try:
            self._reconnect(allow_locked=allow_locked)
        except (LinkLost, *LINK_ERRORS) as exc:
            raise LinkLost(
                f"lost the motion controller at {self.link.url!r} and could not reconnect "
                f"within {self.reconnect_timeout_s:g} s ({exc}). Check the USB cable, then run "
                "`rig-agent resume`."
            ) from exc
        return action()

    # -- protocol ---------------------------------------------------------------------
    def _note(self, line: str, *, raise_alarm: bool = True) -> None:
        """Handle a push message; ``ALARM:N`` raises :class:`GrblAlarm`."""
        if line.startswith("ALARM:"):
            self._locked = True
            if raise_alarm:
                raise GrblAlarm(int(line[6:]))
        self.messages.append(line)

    def send(self, command: str, *, timeout_s: float | None = None) -> list[str]:
        """Send one line and return the lines received before its ``ok``.

        Raises :class:`GrblError` on ``error:N`` and :class:`GrblAlarm` on ``ALARM:N``.
        """
        if "\n" in command or "\r" in command:
            raise ValueError(f"command must be a single line, got {command!r}")
        return self._with_reconnect(
            lambda: self._send(command, timeout_s), allow_locked=command in ("$H", "$X")
        )

    def _send(self, command: str, timeout_s: float | None) -> list[str]:
        self.link.write_line(command)
        deadline = time.monotonic() + (timeout_s or self.command_timeout_s)
        replies: list[str] = []
        while True:
            remaining = deadline - time.monotonic()
            try:
                line = self.link.read_line(timeout_s=max(0.0, remaining))
            except DeviceTimeout as exc:
                raise DeviceTimeout(
                    f"the motion controller did not acknowledge {command!r} within "
                    f"{timeout_s or self.command_timeout_s:g} s; check that it is powered"
                ) from exc
            if line == "ok":
                return replies
            if line.startswith("error:"):
                raise GrblError(int(line[6:]), command)
            if line.startswith("<"):
                continue  # a status report answering an earlier '?'
            self._note(line)
            replies.append(line)

    def status(self) -> GrblStatus:
        """Ask ``?`` and return the report; alarms pushed meanwhile raise."""
        return self._with_reconnect(self._status)

    def _status(self) -> GrblStatus:
        self.link.write(STATUS_QUERY)
        deadline = time.monotonic() + self.command_timeout_s
        while True:
            line = self.link.read_line(timeout_s=max(0.0, deadline - time.monotonic()))
            if line.startswith("<"):
                return parse_status(line)
            if line in ("ok",) or line.startswith("Grbl "):
                continue
            self._note(line)

    def wait_idle(self, *, timeout_s: float) -> GrblStatus:
        """Poll ``?`` until ``Idle``; an ``Alarm`` state or a pushed ``ALARM:N`` raises."""
        deadline = time.monotonic() + timeout_s
        while True:
            status = self.status()
            if status.state == "Idle":
                return status
            if status.state == "Alarm":
                self._locked = True
                raise DeviceError(
                    "the motion controller is in alarm state; run `rig-agent resume` to re-home"
                )
            if time.monotonic() >= deadline:
                raise DeviceTimeout(
                    f"the axes did not come to rest within {timeout_s:g} s "
                    f"(last status {status.raw!r}); check for a stalled motor"
                )
            time.sleep(self.poll_interval_s)

    # -- Stage interface --------------------------------------------------------------
    def needs_homing(self) -> bool:
        return self._locked

    def home(self) -> None:
        """``$H``: GRBL answers ``ok`` once the homing cycle has finished."""
        self.send("$H", timeout_s=self.homing_timeout_s)
        self._locked = False
        self.wait_idle(timeout_s=self.motion_timeout_s)

    def unlock(self) -> None:
        """``$X``: clear the alarm lock without homing (position is not trusted)."""
        self.send("$X")
        self._locked = False

    def move_to(self, *, azimuth_deg: float, elevation_mm: float) -> StagePosition:
        """``G90 G0`` to the absolute target, then wait for ``Idle``."""
        for name, value in (("azimuth_deg", azimuth_deg), ("elevation_mm", elevation_mm)):
            if not isinstance(value, int | float) or value != value or abs(value) == float("inf"):
                raise ValueError(f"{name} must be a finite number, got {value!r}")
        if self._locked:
            raise DeviceError(
                "the motion controller is locked after an alarm or reset; home it first "
                "(`rig-agent resume` does this)"
            )
        self.send(
            f"G90 G0 {self.azimuth_axis}{azimuth_deg:.3f} {self.elevation_axis}{elevation_mm:.3f}"
        )
        status = self.wait_idle(timeout_s=self.motion_timeout_s)
        return self._position_of(status)

    def position(self) -> StagePosition:
        return self._position_of(self.status())

    def _position_of(self, status: GrblStatus) -> StagePosition:
        return StagePosition(
            azimuth_deg=status.mpos.get(self.azimuth_axis, float("nan")),
            elevation_mm=status.mpos.get(self.elevation_axis, float("nan")),
        )
