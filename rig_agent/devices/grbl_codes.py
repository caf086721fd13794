"""GRBL 1.1 error and alarm codes in plain language.

The descriptions follow the tables published with GRBL 1.1
(gnea/grbl ``doc/csv/error_codes_en_US.csv`` and ``alarm_codes_en_US.csv``);
``ADVICE`` adds what the scanner operator should do about the ones a scan meets.
"""

from __future__ import annotations

ERRORS: dict[int, str] = {
    1: "G-code words consist of a letter and a value; a letter was not found",
    2: "a G-code word value is missing or its number format is not valid",
    3: "the '$' system command was not recognised or is not supported",
    4: "a negative value was received where a positive value is expected",
    5: "homing is not enabled in the controller settings ($22)",
    6: "the minimum step pulse time must be greater than 3 µs",
    7: "an EEPROM read failed; the controller restored default settings",
    8: "this '$' command can only be used while the controller is idle",
    9: "G-code commands are locked out while the controller is in alarm or jog state",
    10: "soft limits cannot be enabled without homing also enabled",
    11: "the command line is too long; it was not executed",
    12: "this setting would make the step rate exceed the maximum supported",
    13: "the safety door was detected open",
    14: "the build info or startup line exceeds the EEPROM line length; not stored",
    15: "the jog target exceeds the machine travel; the jog was ignored",
    16: "the jog command has no '=' or contains prohibited G-code",
    17: "laser mode requires PWM output",
    20: "unsupported or invalid G-code command in the block",
    21: "more than one G-code command from the same modal group in the block",
    22: "the feed rate has not been set",
    23: "a G-code command in the block requires an integer value",
    24: "more than one G-code command that requires axis words in the block",
    25: "a G-code word is repeated in the block",
    26: "no axis words in the block for a command that requires them",
    27: "the line number value is invalid",
    28: "a G-code command is missing a required value word",
    29: "G59.x work coordinate systems are not supported",
    30: "G53 is only allowed with G0 and G1 motion modes",
    31: "axis words found in a block where no command uses them",
    32: "G2 and G3 arcs require at least one in-plane axis word",
    33: "the motion command target is invalid",
    34: "the arc radius value is invalid",
    35: "G2 and G3 arcs require at least one in-plane offset word",
    36: "unused value words found in the block",
    37: "G43.1 tool length offset is not assigned to the configured tool length axis",
    38: "the tool number is greater than the maximum supported value",
}

ALARMS: dict[int, str] = {
    1: "a hard limit switch was triggered; the machine position is probably lost",
    2: "the move target is outside the machine travel (soft limit); position retained",
    3: "the controller was reset while moving; the machine position is probably lost",
    4: "probe fail: the probe was not in the expected initial state",
    5: "probe fail: the probe did not make contact within the programmed travel",
    6: "homing failed: the homing cycle was reset",
    7: "homing failed: the safety door was opened during homing",
    8: "homing failed: the pull-off move did not clear the limit switch",
    9: "homing failed: a limit switch was not found within the search distance",
}

ADVICE: dict[int, str] = {
    1: "Check that nothing blocks the light arm or the stage, then run `rig-agent resume` "
    "(it re-homes and continues).",
    2: "The scan plan asks for a position outside the travel configured in the controller; "
    "check the plan's azimuths/elevation and the controller's $130-$132 settings.",
    3: "Run `rig-agent resume`; the axes are re-homed before the scan continues.",
    6: "Run `rig-agent resume` to home again.",
    7: "Close the enclosure door, then run `rig-agent resume`.",
    8: "Check the limit switch wiring or increase the pull-off ($27), then `rig-agent resume`.",
    9: "Check the limit switch and its cable, then `rig-agent resume`.",
}


def describe_error(code: int) -> str:
    """Plain-language text for ``error:code``."""
    return ERRORS.get(code, f"unknown GRBL error code {code}")


def describe_alarm(code: int) -> str:
    """Plain-language text for ``ALARM:code``, with advice when there is some."""
    text = ALARMS.get(code, f"unknown GRBL alarm code {code}")
    advice = ADVICE.get(code)
    return f"{text}. {advice}" if advice else text
