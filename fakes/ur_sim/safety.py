"""The simulated controller's safety system: limits checked before and during motion, and
the stops they trigger.

A command is checked when it is given (joint limits, the mode the arm is in) and every cycle
while it runs (joint and tool speed, safety planes); a breach is a protective stop, as on a
real controller, never a silently clipped motion. Emergency stops brake and then cut power.
"""

from __future__ import annotations

import math
from typing import NoReturn

import numpy as np

from fakes.ur_sim.arm_core import ArmCore
from fakes.ur_sim.state import (
    CommandOutcome,
    CommandRejectedError,
    EmergencyStopActiveError,
    NotRunningError,
    ProtectiveStopActiveError,
    RobotMode,
    SafetyMode,
    SimLimits,
    Vec,
)

LIMIT_MARGIN = 1.02  # profiles ride exactly at the limit; only real excess trips a stop
ESTOP_MODES = (SafetyMode.ROBOT_EMERGENCY_STOP, SafetyMode.SYSTEM_EMERGENCY_STOP)


def check_joint_limits(q: Vec, limits: SimLimits, what: str) -> None:
    """Refuse joints outside the configured limits with a message that names them."""
    if np.any(q < limits.joint_min_rad) or np.any(q > limits.joint_max_rad):
        raise CommandRejectedError(
            f"{what} {np.round(q, 4).tolist()} is outside the joint limits "
            f"[{limits.joint_min_rad:.4f}, {limits.joint_max_rad:.4f}] rad")


class SafetySupervisor:
    """Limits and faults of one arm; every method expects the engine lock held."""

    def __init__(self, core: ArmCore) -> None:
        self._core = core

    # -- checks ------------------------------------------------------------------------------
    def check_joint_limits(self, q: Vec, what: str) -> None:
        check_joint_limits(q, self._core.limits, what)

    def require_motion_allowed(self) -> None:
        """Refuse motion unless the arm is RUNNING in safety mode NORMAL, naming why not."""
        core = self._core
        core.sync_idle_clock()
        if core.safety_mode in ESTOP_MODES:
            raise EmergencyStopActiveError("the arm is emergency-stopped")
        if core.safety_mode == SafetyMode.PROTECTIVE_STOP:
            raise ProtectiveStopActiveError(
                f"the arm is protective-stopped ({core.stop_reason}); unlock it first")
        if core.safety_mode != SafetyMode.NORMAL:
            raise NotRunningError(f"safety mode is {core.safety_mode.name}")
        if core.robot_mode != RobotMode.RUNNING:
            raise NotRunningError(f"robot mode is {core.robot_mode.name}, not RUNNING")

    def violation(self, q: Vec, qd: Vec) -> str:
        """Which run-time limit the next cycle's joints would break ("" if none)."""
        core = self._core
        lim = core.limits
        if np.any(q < lim.joint_min_rad - 1e-9) or np.any(q > lim.joint_max_rad + 1e-9):
            return "joint position limit"
        if float(np.max(np.abs(qd))) > lim.max_joint_speed_rad_s * LIMIT_MARGIN:
            return "joint speed limit"
        T_tcp, J = core.kin.tcp_and_jacobian(q)
        tcp_speed = float(np.linalg.norm((J @ qd)[:3])) / 1000.0
        if tcp_speed > lim.max_tcp_speed_m_s * LIMIT_MARGIN:
            return f"tool speed limit ({tcp_speed:.2f} m/s)"
        outside = self.workspace_excess_m(T_tcp)
        if outside > 0 and outside > self.workspace_excess_m(core.kin.forward_tcp(core.q)):
            return "TCP crossed a safety plane"  # (moving back to the allowed side is allowed)
        return ""

    def workspace_excess_m(self, T_base_tcp: Vec) -> float:
        """How far (m) the TCP is beyond the worst safety plane (<= 0: on the allowed side)."""
        p = T_base_tcp[:3, 3] / 1000.0
        return max((pl.excess_m(p) for pl in self._core.limits.safety_planes),
                   default=-math.inf)

    # -- stops -------------------------------------------------------------------------------
    def trip(self, reason: str) -> NoReturn:
        """A command that would break a safety limit: stop the arm and refuse the command."""
        self.protective_stop(reason, self._core.now())
        raise ProtectiveStopActiveError(f"protective stop: {reason}")

    def protective_stop(self, reason: str, now: float) -> None:
        core = self._core
        core.safety_mode = SafetyMode.PROTECTIVE_STOP
        core.stop_t = now
        core.stop_reason = reason
        core.brake_now(core.limits.protective_stop_decel_rad_s2, "protective_stop",
                       CommandOutcome.ABORTED)

    def emergency_stop(self) -> None:
        """Category-1 stop: brake, then (once at rest) power off."""
        core = self._core
        core.safety_mode = SafetyMode.ROBOT_EMERGENCY_STOP
        core.stop_reason = "emergency stop"
        core.timers = []
        core.brake_now(core.limits.protective_stop_decel_rad_s2, "emergency_stop",
                       CommandOutcome.ABORTED)
        if core.cmd is None:
            core.robot_mode = RobotMode.POWER_OFF

    def trigger_protective_stop(self, reason: str) -> None:
        if self._core.safety_mode not in ESTOP_MODES:
            self.protective_stop(reason, self._core.now())

    def unlock_protective_stop(self) -> bool:
        """Clear a protective stop. False (refused) within ``unlock_delay_s`` of the stop."""
        core = self._core
        if core.safety_mode != SafetyMode.PROTECTIVE_STOP:
            return core.safety_mode == SafetyMode.NORMAL
        assert core.stop_t is not None
        core.sync_idle_clock()
        if core.now() - core.stop_t < core.limits.unlock_delay_s:
            return False
        core.safety_mode = SafetyMode.NORMAL
        core.stop_t = None
        return True

    def release_emergency_stop(self) -> None:
        core = self._core
        if core.safety_mode in ESTOP_MODES:
            core.safety_mode = SafetyMode.NORMAL
            core.stop_t = None
