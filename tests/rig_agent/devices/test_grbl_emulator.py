"""The GRBL emulator on a real pseudo-terminal, spoken to as raw bytes and through the driver."""

from __future__ import annotations

import time

import pytest
import serial

from rig_agent.devices.grbl_emulator import EmulatorConfig, GrblEmulator
from rig_agent.devices.stage import GrblAlarm, GrblStage
from rig_agent.devices.transport import SerialLink


@pytest.fixture
def emulator():
    # 400 units/s: moves last long enough (0.25–0.75 s) to be seen running even on a busy
    # machine, and short enough for a quick test.
    with GrblEmulator(EmulatorConfig(rapid_rate_per_s=400.0)) as emu:
        yield emu


@pytest.fixture
def port(emulator):
    conn = serial.serial_for_url(emulator.port, timeout=0.5)
    conn.reset_input_buffer()
    yield conn
    conn.close()


def ask(conn: serial.Serial, data: bytes, *, lines: int = 1) -> list[str]:
    conn.write(data)
    return [conn.readline().decode().strip() for _ in range(lines)]


def unlocked(conn: serial.Serial) -> None:
    assert ask(conn, b"$X\n", lines=2) == ["[MSG:Caution: Unlocked]", "ok"]


def test_reset_prints_welcome_and_homing_lock(port):
    port.write(b"\x18")
    assert port.readline() == b"\r\n"
    assert port.readline().decode().strip() == "Grbl 1.1h ['$' for help]"
    assert port.readline().decode().strip() == "[MSG:'$H'|'$X' to unlock]"
    assert ask(port, b"?") == ["<Alarm|MPos:0.000,0.000,0.000|FS:0,0>"]


def test_gcode_is_locked_until_homed_or_unlocked(port):
    assert ask(port, b"G0 X1\n") == ["error:9"]
    assert ask(port, b"$H\n") == ["ok"]
    assert ask(port, b"?") == ["<Idle|MPos:0.000,0.000,0.000|FS:0,0>"]


@pytest.mark.parametrize(
    ("line", "reply"),
    [
        (b"5\n", "error:1"),  # expected command letter
        (b"G0 X\n", "error:2"),  # bad number format
        (b"$Q\n", "error:3"),  # invalid statement
        (b"G1 F-5\n", "error:4"),  # negative value
        (b"G1 X1\n", "error:22"),  # undefined feed rate
        (b"G0 G1 X1\n", "error:21"),  # modal group violation
        (b"G5 X1\n", "error:20"),  # unsupported command
        (b"M3\n", "error:20"),
        (b"X1 X2\n", "error:25"),  # repeated word
        (b"G4\n", "error:28"),  # dwell without P
        (b"G0 X1 (comment) ; more\n", "ok"),
        (b"\n", "ok"),
        (b"G0 X" + b"1" * 90 + b"\n", "error:11"),  # line overflow
    ],
)
def test_gcode_errors_as_grbl_reports_them(port, line, reply):
    unlocked(port)
    assert ask(port, line) == [reply]


def wait_idle(conn: serial.Serial) -> str:
    deadline = time.monotonic() + 10
    while time.monotonic() < deadline:
        (report,) = ask(conn, b"?")
        if report.startswith("<Idle|"):
            return report
        time.sleep(0.02)
    raise AssertionError("the emulator never came to rest")


def test_moves_take_time_and_report_run_then_idle(port):
    unlocked(port)
    assert ask(port, b"G90 G0 X200 Z10\n") == ["ok"]
    assert ask(port, b"?")[0].startswith("<Run|")
    assert wait_idle(port) == "<Idle|MPos:200.000,0.000,10.000|FS:0,0>"
    assert ask(port, b"G91 G0 X-50\n") == ["ok"]
    assert wait_idle(port) == "<Idle|MPos:150.000,0.000,10.000|FS:0,0>"


def test_soft_limit_is_a_critical_alarm_until_reset(port):
    unlocked(port)
    assert ask(port, b"G0 X400\n", lines=2) == ["ALARM:2", "[MSG:Reset to continue]"]
    port.write(b"G0 X1\n")  # ignored: GRBL only reads real-time commands now
    assert ask(port, b"?") == ["<Alarm|MPos:0.000,0.000,0.000|FS:0,0>"]
    assert ask(port, b"\x18", lines=3)[1:] == [
        "Grbl 1.1h ['$' for help]",
        "[MSG:'$H'|'$X' to unlock]",
    ]


def test_hard_limit_half_way_through_a_move(port, emulator):
    unlocked(port)
    emulator.hard_limit_on_move = 1
    assert ask(port, b"G0 X300\n") == ["ok"]
    assert [port.readline().decode().strip() for _ in range(2)] == [
        "ALARM:1",
        "[MSG:Reset to continue]",
    ]
    assert ask(port, b"?") == ["<Alarm|MPos:150.000,0.000,0.000|FS:0,0>"]


def test_reset_during_motion_is_alarm_3(port):
    unlocked(port)
    ask(port, b"G0 X300\n")
    assert ask(port, b"\x18", lines=3)[:2] == ["ALARM:3", ""]


def test_settings_and_build_info(port):
    assert ask(port, b"$I\n", lines=3) == ["[VER:1.1h.20190830:]", "[OPT:V,15,128]", "ok"]
    assert ask(port, b"$$\n", lines=6)[-1] == "ok"


def test_driver_over_the_pty_homes_moves_and_survives_an_alarm(emulator):
    stage = GrblStage(SerialLink(emulator.port), poll_interval_s=0.005)
    stage.connect()
    try:
        assert stage.needs_homing()
        stage.home()
        assert stage.move_to(azimuth_deg=90, elevation_mm=5).azimuth_deg == 90.0
        emulator.hard_limit_on_move = 2
        with pytest.raises(GrblAlarm, match="hard limit"):
            stage.move_to(azimuth_deg=180, elevation_mm=5)
        stage.connect()  # what `rig-agent resume` does: reset, then home
        assert stage.needs_homing()
        stage.home()
        assert stage.move_to(azimuth_deg=180, elevation_mm=5).azimuth_deg == 180.0
    finally:
        stage.close()
    assert emulator.received[-1] == "G90G0X180.000Z5.000"


def test_spy_url_logs_the_traffic_of_the_same_driver(emulator, capsys):
    stage = GrblStage(SerialLink(f"spy://{emulator.port}"), poll_interval_s=0.005)
    stage.connect()
    try:
        stage.home()
        stage.send("$I")
    finally:
        stage.close()
    logged = capsys.readouterr().err
    assert "TX   0000  24 48 0A" in logged  # "$H\n"
    assert "TX   0000  24 49 0A" in logged  # "$I\n"
    assert "VER:1.1h" in logged  # the ASCII column of the received bytes
