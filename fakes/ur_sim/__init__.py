"""Simulated UR5e physics: kinematics, velocity profiles and the real-time motion engine.

No network here: the protocol servers in ``fakes.ur_controller`` and ``fakes.sim_arm`` drive
:class:`MotionEngine`.
"""

from fakes.ur_sim.engine import (
    HOME_Q_RAD,
    CommandOutcome,
    CommandRejectedError,
    EmergencyStopActiveError,
    EngineError,
    EngineSnapshot,
    MotionEngine,
    NotRunningError,
    ProtectiveStopActiveError,
    RobotMode,
    SafetyMode,
    SafetyPlane,
    SimLimits,
    UnreachablePoseError,
)

__all__ = [
    "HOME_Q_RAD",
    "CommandOutcome",
    "CommandRejectedError",
    "EmergencyStopActiveError",
    "EngineError",
    "EngineSnapshot",
    "MotionEngine",
    "NotRunningError",
    "ProtectiveStopActiveError",
    "RobotMode",
    "SafetyMode",
    "SafetyPlane",
    "SimLimits",
    "UnreachablePoseError",
]
