"""Power, brakes and the robot-mode transitions of the simulated controller.

Powering on and releasing the brakes take time on a real arm (POWER_OFF -> POWER_ON -> IDLE ->
RUNNING), and a client that commands motion too early is refused. The transitions, and the
faults a test injects mid-move, are events on the controller clock, run by the cycle thread.
"""

from __future__ import annotations

import numpy as np

from fakes.ur_sim.arm_core import ArmCore
from fakes.ur_sim.safety import ESTOP_MODES, SafetySupervisor
from fakes.ur_sim.state import (
    CommandOutcome,
    CommandRejectedError,
    EmergencyStopActiveError,
    FaultKind,
    RobotMode,
)


class PowerControl:
    """Power and brake state of one arm, and its scheduled events; callers hold the lock."""

    def __init__(self, core: ArmCore, safety: SafetySupervisor) -> None:
        self._core = core
        self._safety = safety

    def power_on(self) -> None:
        """POWER_OFF -> POWER_ON -> IDLE after ``limits.power_on_s``. Refused under e-stop."""
        core = self._core
        if core.safety_mode in ESTOP_MODES:
            raise EmergencyStopActiveError("release the emergency stop before powering on")
        if core.robot_mode == RobotMode.POWER_OFF:
            core.robot_mode = RobotMode.POWER_ON
            core.sync_idle_clock()
            core.timers.append((core.now() + core.limits.power_on_s, "idle"))
            core.cond.notify_all()

    def power_off(self) -> None:
        """Brakes on at once (any motion ends where it is) -> POWER_OFF."""
        core = self._core
        core.finish(CommandOutcome.ABORTED)
        core.qd = np.zeros(6)
        core.qdd = np.zeros(6)
        core.timers = [(t, e) for t, e in core.timers if e not in ("idle", "running")]
        core.robot_mode = RobotMode.POWER_OFF
        core.cond.notify_all()

    def brake_release(self) -> None:
        """Release the brakes: (POWER_OFF ->) POWER_ON -> IDLE -> RUNNING, taking a moment."""
        core = self._core
        if core.robot_mode == RobotMode.RUNNING:
            return
        self.power_on()
        idle_due = max([t for t, e in core.timers if e == "idle"], default=core.now())
        core.timers.append((idle_due + core.limits.brake_release_s, "running"))
        core.cond.notify_all()

    def inject(self, fault: FaultKind, after_s: float) -> None:
        """Schedule a fault ``after_s`` from now (e.g. mid-move)."""
        if fault not in ("protective_stop", "emergency_stop"):
            raise CommandRejectedError(f"unknown fault {fault!r}")
        core = self._core
        core.sync_idle_clock()
        core.timers.append((core.now() + max(0.0, float(after_s)), fault))
        core.cond.notify_all()

    def run_timers(self, now: float) -> None:
        """Carry out the events due by ``now`` on the controller clock."""
        core = self._core
        due = [e for t, e in core.timers if t <= now]
        if not due:
            return
        core.timers = [(t, e) for t, e in core.timers if t > now]
        for event in due:
            if event == "idle" and core.robot_mode == RobotMode.POWER_ON:
                core.robot_mode = RobotMode.IDLE
            elif event == "running" and core.robot_mode in (RobotMode.POWER_ON, RobotMode.IDLE):
                core.robot_mode = RobotMode.RUNNING
            elif event == "protective_stop":
                self._safety.protective_stop("injected protective stop", now)
            elif event == "emergency_stop":
                self._safety.emergency_stop()
        core.cond.notify_all()
