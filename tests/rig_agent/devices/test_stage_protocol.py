"""GrblStage against command/response pairs from the GRBL 1.1 interface documentation."""

from __future__ import annotations

import pytest
import serial

from rig_agent.devices.base import DeviceError, DeviceTimeout, StagePosition
from rig_agent.devices.grbl_codes import ALARMS, ERRORS, describe_error
from rig_agent.devices.stage import GrblAlarm, GrblError, parse_status
from rig_agent.devices.transport import LinkLost, SerialLink

WELCOME = b"\r\nGrbl 1.1h ['$' for help]\r\n"
LOCKED = b"[MSG:'$H'|'$X' to unlock]\r\n"
IDLE0 = b"<Idle|MPos:0.000,0.000,0.000|FS:0,0>\r\n"
ALARM0 = b"<Alarm|MPos:0.000,0.000,0.000|FS:0,0>\r\n"


def test_connect_soft_resets_and_sees_the_homing_lock(scripted, connection):
    conn = connection([(b"\x18", WELCOME + LOCKED), (b"?", ALARM0)])
    stage, _ = scripted(conn)
    stage.soft_reset()
    assert stage.needs_homing()
    assert "[MSG:'$H'|'$X' to unlock]" in stage.messages
    assert conn.script == []


def test_home_waits_for_ok_then_idle(scripted, connection):
    conn = connection([(b"$H\n", b"ok\r\n"), (b"?", IDLE0)])
    stage, _ = scripted(conn)
    stage.home()
    assert not stage.needs_homing()
    assert conn.script == []


def test_move_sends_absolute_rapid_and_polls_until_idle(scripted, connection):
    conn = connection(
        [
            (b"G90 G0 X45.000 Z2.500\n", b"ok\r\n"),
            (b"?", b"<Run|MPos:20.000,0.000,1.000|FS:500,0>\r\n"),
            (b"?", b"<Run|MPos:40.000,0.000,2.000|FS:500,0>\r\n"),
            (b"?", b"<Idle|MPos:45.000,0.000,2.500|FS:0,0>\r\n"),
        ]
    )
    stage, _ = scripted(conn)
    stage._locked = False
    assert stage.move_to(azimuth_deg=45, elevation_mm=2.5) == StagePosition(45.0, 2.5)
    assert conn.script == []


def test_axes_are_configurable(scripted, connection):
    conn = connection([(b"G90 G0 Y10.000 X1.000\n", b"ok\r\n"), (b"?", IDLE0)])
    stage, _ = scripted(conn, azimuth_axis="Y", elevation_axis="X")
    stage._locked = False
    stage.move_to(azimuth_deg=10, elevation_mm=1)
    assert conn.script == []


@pytest.mark.parametrize("code", sorted(ERRORS))
def test_every_error_code_becomes_a_plain_message(scripted, connection, code):
    conn = connection([(b"G90 G0 X1.000 Z0.000\n", f"error:{code}\r\n".encode())])
    stage, _ = scripted(conn)
    stage._locked = False
    with pytest.raises(GrblError) as info:
        stage.move_to(azimuth_deg=1, elevation_mm=0)
    assert info.value.code == code
    message = str(info.value)
    assert describe_error(code) in message and "G90 G0 X1.000 Z0.000" in message
    assert f"error:{code}" in message


@pytest.mark.parametrize("code", sorted(ALARMS))
def test_an_alarm_pushed_during_motion_stops_with_its_meaning(scripted, connection, code):
    conn = connection(
        [
            (b"G90 G0 X90.000 Z0.000\n", b"ok\r\n"),
            (b"?", f"ALARM:{code}\r\n[MSG:Reset to continue]\r\n".encode() + ALARM0),
        ]
    )
    stage, _ = scripted(conn)
    stage._locked = False
    with pytest.raises(GrblAlarm) as info:
        stage.move_to(azimuth_deg=90, elevation_mm=0)
    assert info.value.code == code
    assert ALARMS[code] in str(info.value)
    assert stage.needs_homing()


def test_hard_limit_message_tells_the_operator_what_to_do(scripted, connection):
    conn = connection([(b"G90 G0 X90.000 Z0.000\n", b"ALARM:1\r\n")])
    stage, _ = scripted(conn)
    stage._locked = False
    with pytest.raises(GrblAlarm, match="rig-agent resume"):
        stage.move_to(azimuth_deg=90, elevation_mm=0)


def test_unlock_accepts_the_caution_message(scripted, connection):
    conn = connection([(b"$X\n", b"[MSG:Caution: Unlocked]\r\nok\r\n")])
    stage, _ = scripted(conn)
    stage.unlock()
    assert not stage.needs_homing()
    assert "[MSG:Caution: Unlocked]" in stage.messages


def test_build_info_lines_are_returned_before_ok(scripted, connection):
    conn = connection([(b"$I\n", b"[VER:1.1h.20190830:]\r\n[OPT:V,15,128]\r\nok\r\n")])
    stage, _ = scripted(conn)
    assert stage.send("$I") == ["[VER:1.1h.20190830:]", "[OPT:V,15,128]"]


def test_silence_is_a_timeout_naming_the_command(scripted, connection):
    conn = connection([(b"$I\n", b"")])
    stage, _ = scripted(conn, command_timeout_s=0.05)
    with pytest.raises(DeviceTimeout, match=r"\$I"):
        stage.send("$I")


def test_motion_that_never_ends_times_out(scripted, connection):
    run = b"<Run|MPos:1.000,0.000,0.000|FS:500,0>\r\n"
    conn = connection([(b"G90 G0 X9.000 Z0.000\n", b"ok\r\n")] + [(b"?", run)] * 200)
    stage, _ = scripted(conn, motion_timeout_s=0.05, poll_interval_s=0.01)
    stage._locked = False
    with pytest.raises(DeviceTimeout, match="did not come to rest"):
        stage.move_to(azimuth_deg=9, elevation_mm=0)


def test_a_locked_stage_refuses_to_move(scripted, connection):
    stage, _ = scripted(connection([]))
    with pytest.raises(DeviceError, match="home it first"):
        stage.move_to(azimuth_deg=0, elevation_mm=0)


@pytest.mark.parametrize("bad", [float("nan"), float("inf"), "10"])
def test_move_rejects_non_finite_targets(scripted, connection, bad):
    stage, _ = scripted(connection([]))
    stage._locked = False
    with pytest.raises(ValueError, match="azimuth_deg"):
        stage.move_to(azimuth_deg=bad, elevation_mm=0)


def test_usb_drop_reopens_by_url_resyncs_and_retries(scripted, connection):
    dropped = connection([], fail_on=b"G90 G0 X30.000 Z0.000\n")
    fresh = connection(
        [
            (b"?", IDLE0),
            (b"G90 G0 X30.000 Z0.000\n", b"ok\r\n"),
            (b"?", b"<Idle|MPos:30.000,0.000,0.000|FS:0,0>\r\n"),
        ]
    )
    stage, opener = scripted(dropped, fresh)
    stage._locked = False
    assert stage.move_to(azimuth_deg=30, elevation_mm=0).azimuth_deg == 30.0
    assert opener.urls == ["/dev/ttyFAKE0", "/dev/ttyFAKE0"]
    assert dropped.closed and fresh.script == []


def test_usb_drop_that_reset_the_board_asks_for_resume(scripted, connection):
    dropped = connection([], fail_on=b"G90 G0 X30.000 Z0.000\n")
    rebooted = connection([(b"?", ALARM0)])
    stage, _ = scripted(dropped, rebooted)
    stage._locked = False
    with pytest.raises(DeviceError, match="restarted after its USB connection dropped"):
        stage.move_to(azimuth_deg=30, elevation_mm=0)
    assert stage.needs_homing()


def test_usb_drop_without_the_device_coming_back_is_a_clear_error(scripted, connection):
    stage, _ = scripted(connection([], fail_on=b"$I\n"))
    with pytest.raises(LinkLost, match="could not reconnect"):
        stage.send("$I")


def test_opening_a_missing_port_names_the_url():
    link = SerialLink("/dev/does-not-exist-rig-agent", timeout_s=0.01)
    with pytest.raises(LinkLost, match="does-not-exist-rig-agent"):
        link.open()


def test_link_reads_lines_over_pyserial_loop_handler():
    link = SerialLink("loop://", timeout_s=0.01, opener=serial.serial_for_url)
    link.open()
    try:
        link.write(b"\r\nok\r\n<Idle|MPos:1.000,2.000,3.000|FS:0,0>\r\n")
        assert link.read_line(timeout_s=1) == "ok"
        status = parse_status(link.read_line(timeout_s=1))
        assert status.state == "Idle" and status.mpos == {"X": 1.0, "Y": 2.0, "Z": 3.0}
        with pytest.raises(DeviceTimeout):
            link.read_line(timeout_s=0.02)
    finally:
        link.close()


def test_parse_status_variants():
    assert parse_status("<Hold:0|MPos:1.5,0,-2|Bf:15,128|FS:0,0>").state == "Hold"
    assert parse_status("<Idle|WPos:0.000,1.000,2.000>").mpos["Z"] == 2.0
    with pytest.raises(ValueError, match="not a GRBL status report"):
        parse_status("ok")


def test_multi_line_commands_are_refused(scripted, connection):
    stage, _ = scripted(connection([]))
    with pytest.raises(ValueError, match="single line"):
        stage.send("G0 X1\nG0 X2")


def test_homing_goes_on_after_a_usb_drop_that_reset_the_board(scripted, connection):
    dropped = connection([], fail_on=b"$H\n")
    rebooted = connection([(b"?", ALARM0), (b"$H\n", b"ok\r\n"), (b"?", IDLE0)])
    stage, _ = scripted(dropped, rebooted)
    stage.home()
    assert not stage.needs_homing() and rebooted.script == []
