"""Universal Robots e-Series through ur_rtde: the adapter, the ur_rtde child process that
hosts the RTDE clients and the controller's watchdog, and the controller's codes."""

from drivers.ur.adapter import URArm

__all__ = ["URArm"]
