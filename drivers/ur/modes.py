"""UR controller codes as the RTDE interface reports them, in one place for the driver side.

Values are UR's published ones (RTDE guide: ``robot_mode``, ``safety_mode``,
``safety_status_bits``, ``runtime_state``); names are what the cell shows an operator.
"""

from __future__ import annotations

from enum import IntEnum, IntFlag


class RobotMode(IntEnum):
    NO_CONTROLLER = -1
    DISCONNECTED = 0
    CONFIRM_SAFETY = 1
    BOOTING = 2
    POWER_OFF = 3
    POWER_ON = 4
    IDLE = 5
    BACKDRIVE = 6
    RUNNING = 7
    UPDATING_FIRMWARE = 8


class SafetyMode(IntEnum):
    NORMAL = 1
    REDUCED = 2
    PROTECTIVE_STOP = 3
    RECOVERY = 4
    SAFEGUARD_STOP = 5
    SYSTEM_EMERGENCY_STOP = 6
    ROBOT_EMERGENCY_STOP = 7
    VIOLATION = 8
    FAULT = 9
    VALIDATE_JOINT_ID = 10
    UNDEFINED_SAFETY_MODE = 11
    AUTOMATIC_MODE_SAFEGUARD_STOP = 12
    SYSTEM_THREE_POSITION_ENABLING_STOP = 13


class SafetyBits(IntFlag):
    NORMAL = 1 << 0
    REDUCED = 1 << 1
    PROTECTIVE_STOPPED = 1 << 2
    RECOVERY = 1 << 3
    SAFEGUARD_STOPPED = 1 << 4
    SYSTEM_EMERGENCY_STOPPED = 1 << 5
    ROBOT_EMERGENCY_STOPPED = 1 << 6
    EMERGENCY_STOPPED = 1 << 7
    VIOLATION = 1 << 8
    FAULT = 1 << 9
    STOPPED_DUE_TO_SAFETY = 1 << 10


ESTOP_BITS = (SafetyBits.SYSTEM_EMERGENCY_STOPPED | SafetyBits.ROBOT_EMERGENCY_STOPPED
              | SafetyBits.EMERGENCY_STOPPED)


class RuntimeState(IntEnum):
    STOPPING = 0
    STOPPED = 1
    PLAYING = 2
    PAUSING = 3
    PAUSED = 4
    RESUMING = 5


def robot_mode_name(code: int) -> str:
    try:
        return RobotMode(code).name
    except ValueError:
        return "UNKNOWN"


def safety_mode_name(code: int) -> str:
    try:
        return SafetyMode(code).name
    except ValueError:
        return "UNKNOWN"
