"""The simulated arm's state and its one lock, shared by the parts of the motion engine.

The engine is split by responsibility (the cycle thread, safety, power and modes, snapshots,
planning, the command API), but there is one arm: every part reads and writes this state under
this lock. Besides the state it holds the few operations on the active-command slot that every
part needs (install, finish, brake), so no part reaches into another's fields.

Every method here expects the caller to hold ``cond`` (a re-entrant lock).
"""

from __future__ import annotations

import threading
from collections import deque
from collections.abc import Callable

import numpy as np

from estimator.transforms import T_from_ur_pose
from fakes.ur_sim.clock import CycleClock
from fakes.ur_sim.commands import Brake, Command, Then
from fakes.ur_sim.kinematics import UnreachableError, UR5eKinematics
from fakes.ur_sim.state import (
    CYCLE_S,
    CommandOutcome,
    Pose6,
    RobotMode,
    SafetyMode,
    SimLimits,
    UnreachablePoseError,
    Vec,
)
from fakes.ur_sim.step_context import StepContext

_HISTORY_S = 10.0
_MAX_OUTCOMES = 1000  # outcomes kept; the oldest half goes when there are more


class ArmCore:
    """Joints, modes, the active command and the controller clock of one simulated arm."""

    def __init__(self, q: Vec, limits: SimLimits) -> None:
        self.limits = limits
        self.kin = UR5eKinematics(joint_min_rad=limits.joint_min_rad,
                                  joint_max_rad=limits.joint_max_rad)
        self.cond = threading.Condition()
        self.q = q
        self.qd = np.zeros(6)
        self.qdd = np.zeros(6)
        self.tcp_offset: Pose6 = [0.0] * 6
        self.robot_mode = RobotMode.POWER_OFF
        self.safety_mode = SafetyMode.NORMAL
        self.stop_t: float | None = None
        self.stop_reason = ""
        self.program_running = False
        self.speed_fraction = 1.0
        self.cmd: Command | None = None
        self.next_id = 1
        self.outcomes: dict[int, CommandOutcome] = {}
        self.timers: list[tuple[float, str]] = []  # (due monotonic, event)
        self.clock = CycleClock()
        # the protocol layer's per-cycle hook (see MotionEngine.set_cycle_hook)
        self.hook: Callable[[], None] | None = None
        self.hook_wants: Callable[[], bool] | None = None
        self.idle_period_s = 0.02
        self.history: deque[tuple[float, Vec]] = deque(maxlen=int(_HISTORY_S / CYCLE_S))
        self.history.append((self.clock.t0, self.q.copy()))
        self.alive = True

    # -- clock -------------------------------------------------------------------------------
    def busy(self) -> bool:
        return self.cmd is not None

    def cycling(self) -> bool:
        """Whether every controller cycle must run: something moves, or the hook needs it."""
        wants = self.hook_wants
        return self.busy() or (self.hook is not None and wants is not None and wants())

    def now(self) -> float:
        return self.clock.now()

    def sync_idle_clock(self) -> None:
        """An idle controller's clock is simply the present (no cycle to catch up)."""
        if not self.cycling():
            self.clock.cycles = max(self.clock.cycles, self.clock.due())

    # -- the active command ------------------------------------------------------------------
    def step_context(self) -> StepContext:
        """The read-only view of the arm a command steps from."""
        return StepContext(self.q, self.qd, self.speed_fraction, self.kin, self.limits)

    def new_id(self) -> int:
        """The id the next installed command gets; consumed only by :meth:`install`, so a
        rejected command leaves no trace."""
        return self.next_id

    def finish(self, outcome: CommandOutcome, then: Command | None = None) -> None:
        """End the active command with ``outcome`` (if still running); ``then`` runs next."""
        if self.cmd is not None and self.outcomes.get(self.cmd.id) == CommandOutcome.RUNNING:
            self.outcomes[self.cmd.id] = outcome
        self.cmd = then
        self.cond.notify_all()

    def brake_now(self, decel: float, name: str, outcome: CommandOutcome) -> None:
        """End the active command, braking from the present velocity."""
        brake = Brake(0, name, self.q, self.qd, decel)
        self.finish(outcome, brake if brake.T > 0 else None)
        if self.cmd is None:
            self.qd = np.zeros(6)
            self.qdd = np.zeros(6)
        self.cond.notify_all()

    def rest_start(self, accel: float) -> tuple[Vec, Brake | None]:
        """Where a profiled move will start: here, or where the present motion brakes to."""
        if self.cmd is None and not np.any(self.qd):
            return self.q.copy(), None
        brake = Brake(0, "brake", self.q, self.qd, max(accel, 1.0))
        return brake.q_end, brake

    def install(self, cmd: Command, brake: Brake | None = None) -> int:
        """Make ``cmd`` the active command (after ``brake``), preempting the present one."""
        self.finish(CommandOutcome.PREEMPTED)
        self.next_id = cmd.id + 1
        self.outcomes[cmd.id] = CommandOutcome.RUNNING
        if len(self.outcomes) > _MAX_OUTCOMES:
            for old in sorted(self.outcomes)[:_MAX_OUTCOMES // 2]:
                del self.outcomes[old]
        self.cmd = Then(brake, cmd) if brake is not None and brake.T > 0 else cmd
        self.cond.notify_all()
        return cmd.id

    # -- kinematics --------------------------------------------------------------------------
    def ik(self, pose6: Vec, seed: Vec) -> Vec:
        """Joints reaching a UR pose6 nearest ``seed``, as the engine's typed error."""
        try:
            return self.kin.inverse_tcp(T_from_ur_pose(pose6.tolist()), seed)
        except UnreachableError as err:
            raise UnreachablePoseError(f"pose {list(pose6)} is unreachable: {err}") from err
