"""Typed turntable errors and the GRBL 1.1 error/alarm tables they carry.

Every `error:N` and `ALARM:N` the firmware sends becomes one exception carrying the code and
the firmware's own meaning (texts from GRBL 1.1's error_codes_en_US.csv / alarm_codes_en_US.csv),
the way rawpy maps LibRaw codes to typed exceptions. All are DeviceErrors (exit code 3) except
a tilt target outside the configured limits, which is the caller's bad input (exit code 2).
"""

from __future__ import annotations

from station.errors import BadInputError, DeviceError, StationError

GRBL_ERRORS: dict[int, str] = {
    1: "Expected command letter: G-code words consist of a letter and a value; letter was not found",
    2: "Bad number format: missing the expected G-code word value or numeric value format is not valid",
    3: "Invalid statement: Grbl '$' system command was not recognized or supported",
    4: "Value < 0: negative value received for an expected positive value",
    5: "Setting disabled: homing cycle is not enabled via settings",
    6: "Value < 3 usec: minimum step pulse time must be greater than 3 usec",
    7: "EEPROM read fail: restoring affected EEPROM to default values",
    8: "Not idle: Grbl '$' command cannot be used unless Grbl is IDLE",
    9: "G-code lock: G-code commands are locked out during alarm or jog state",
    10: "Homing not enabled: soft limits cannot be enabled without homing also enabled",
    11: "Line overflow: max characters per line exceeded; line was not executed",
    12: "Step rate > 30kHz: setting value causes the step rate to exceed the maximum supported",
    13: "Check door: safety door detected as opened and door state initiated",
    14: "Line length exceeded: build info or startup line exceeded EEPROM line length limit",
    15: "Travel exceeded: jog target exceeds machine travel; jog command has been ignored",
    16: "Invalid jog command: jog command has no '=' or contains prohibited g-code",
    17: "Setting disabled: laser mode requires PWM output",
    20: "Unsupported command: unsupported or invalid g-code command found in block",
    21: "Modal group violation: more than one g-code command from same modal group found in block",
    22: "Undefined feed rate: feed rate has not yet been set or is undefined",
    23: "Invalid gcode ID:23: G-code command in block requires an integer value",
    24: "Invalid gcode ID:24: more than one g-code command that requires axis words found in block",
    25: "Invalid gcode ID:25: repeated g-code word found in block",
    26: "Invalid gcode ID:26: no axis words found in block for g-code command or modal state which requires them",
    27: "Invalid gcode ID:27: line number value is invalid",
    28: "Invalid gcode ID:28: G-code command is missing a required value word",
    29: "Invalid gcode ID:29: G59.x work coordinate systems are not supported",
    30: "Invalid gcode ID:30: G53 only allowed with G0 and G1 motion modes",
    31: "Invalid gcode ID:31: axis words found in block when no command or modal state uses them",
    32: "Invalid gcode ID:32: G2 and G3 arcs require at least one in-plane axis word",
    33: "Invalid gcode ID:33: motion command target is invalid",
    34: "Invalid gcode ID:34: arc radius value is invalid",
    35: "Invalid gcode ID:35: G2 and G3 arcs require at least one in-plane offset word",
    36: "Invalid gcode ID:36: unused value words found in block",
    37: "Invalid gcode ID:37: G43.1 dynamic tool length offset is not assigned to configured tool length axis",
    38: "Invalid gcode ID:38: tool number greater than max supported value",
}

GRBL_ALARMS: dict[int, str] = {
    1: "Hard limit triggered; machine position is likely lost due to sudden halt, re-homing is highly recommended",
    2: "Soft limit: G-code motion target exceeds machine travel; machine position retained, reset to continue",
    3: "Reset while in motion; machine position is likely lost due to sudden halt, re-homing is highly recommended",
    4: "Probe fail: probe is not in the expected initial state before starting probe cycle",
    5: "Probe fail: probe did not contact the workpiece within the programmed travel",
    6: "Homing fail: the active homing cycle was reset",
    7: "Homing fail: safety door was opened during homing cycle",
    8: "Homing fail: pull off travel failed to clear limit switch",
    9: "Homing fail: could not find limit switch within search distances",
    10: "Homing fail: second dual axis limit switch failed to trigger within configured search distance",
}


class GrblError(DeviceError):
    """The firmware answered `error:N` to a line; `code` and `meaning` come from GRBL's table."""

    def __init__(self, code: int, line: str, port: str) -> None:
        self.code, self.line, self.port = code, line, port
        self.meaning = GRBL_ERRORS.get(code, "unknown error code")
        super().__init__(f"turntable on {port} refused {line!r}: error:{code} ({self.meaning})")


class GrblAlarm(DeviceError):
    """The firmware raised `ALARM:N`; motion stopped and the machine is locked until reset/unlock."""

    def __init__(self, code: int, port: str) -> None:
        self.code, self.port = code, port
        self.meaning = GRBL_ALARMS.get(code, "unknown alarm code")
        super().__init__(f"turntable on {port} raised ALARM:{code} ({self.meaning})")


class NotGrblError(DeviceError):
    """Something answered on the port, but not a GRBL/grblHAL banner: wrong port or wrong device."""

    def __init__(self, port: str, heard: str) -> None:
        self.port, self.heard = port, heard
        super().__init__(f"{port} does not answer like GRBL 1.1 or grblHAL (heard {heard!r}); wrong port?")


class GrblSettingsError(DeviceError):
    """`$$` settings differ from the rig's expected config (steps/degree, rates, accelerations)."""


class GarbledStatusError(DeviceError):
    """A `?` status report could not be parsed (partial or corrupted line)."""


class UnexpectedResetError(DeviceError):
    """The firmware printed its banner mid-session: the board reset itself, position may be lost."""


class TiltLimitError(BadInputError):
    """A tilt target lies outside the configured mechanical limits; nothing was sent."""


class SoftLimitError(BadInputError):
    """A target lies outside the board's soft-limit travel ($20/$130/$131) or the X window; nothing was sent."""


class ReferenceMismatchError(DeviceError):
    """The board's work offset (status `WCO`) disagrees with its stored G54 reference (`$#`)."""


class WaitTimeoutError(TimeoutError, StationError):
    """The caller stopped waiting on a status; the device itself has not failed (ophyd's split)."""

    exit_code = 2


class MoveCancelledError(StationError):
    """The operator cancelled the move; the table was held and stopped without losing position."""

    exit_code = 2
