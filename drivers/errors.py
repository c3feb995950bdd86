"""Typed hardware errors: the cell maps each to a state and an API status."""

from __future__ import annotations


class DriverError(Exception):
    """Base class for hardware faults and refusals."""

    code = "driver_error"


class ConnectionLostError(DriverError):
    """The device or controller is unreachable or stopped answering."""

    code = "connection_lost"


class NotReadyError(DriverError):
    """The device is connected but not in a state that accepts the command (e.g. not in remote)."""

    code = "not_ready"


class UnlockTooEarlyError(NotReadyError):
    """The controller refuses to unlock a protective stop this soon after it happened."""

    code = "unlock_too_early"

    def __init__(self, message: str, retry_in_s: float) -> None:
        super().__init__(message)
        self.retry_in_s = retry_in_s


class ProtectiveStopError(DriverError):
    """The arm is protective-stopped; motion is refused until recovered."""

    code = "protective_stop"


class EmergencyStopError(DriverError):
    """The arm is emergency-stopped; needs a person at the cell."""

    code = "emergency_stop"


class MotionError(DriverError):
    """A motion command was rejected or did not complete (limits, unreachable pose, aborted)."""

    code = "motion_failed"


class ControllerWatchdogError(MotionError):
    """The controller's RTDE watchdog ended the control script: the host stopped writing to
    it for longer than the watchdog allows (a starved or frozen host), so the arm braked."""

    code = "controller_watchdog"


class DeviceTimeoutError(DriverError):
    """The device did not answer in time."""

    code = "device_timeout"


class ProtocolError(DriverError):
    """The device answered with something that is not the expected protocol (CRC, garbage)."""

    code = "protocol_error"
