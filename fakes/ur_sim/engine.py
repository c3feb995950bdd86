"""The physical half of the simulated UR e-Series controller: a real-time motion engine.

The protocol servers (RTDE, script mailbox, dashboard) in ``fakes.ur_controller`` and the
in-process :class:`fakes.sim_arm.SimArm` both drive this one engine, so every client sees the
same arm. A background thread steps the arm at 500 Hz of wall-clock time (``time.monotonic``):
moves take the time their velocity profile says, a client that stops streaming servo/speed
commands sees the arm brake, and safety limits trip protective stops the way a controller's
safety system does. When nothing moves the thread sleeps on a condition, so an idle engine
costs next to no CPU on a shared machine.

:class:`MotionEngine` is the one face of the simulated arm; the work is done by parts with one
job each, sharing one :class:`~fakes.ur_sim.arm_core.ArmCore` (state and lock): the cycle thread
(:mod:`~fakes.ur_sim.cycle_loop`, :mod:`~fakes.ur_sim.clock`), limits and stops
(:mod:`~fakes.ur_sim.safety`), power and brakes (:mod:`~fakes.ur_sim.power`), RTDE snapshots
(:mod:`~fakes.ur_sim.snapshots`), move planning (:mod:`~fakes.ur_sim.planning`) and the motion
commands (:mod:`~fakes.ur_sim.command_api`).

Units at this API are UR's wire units so the protocol layer can pass values through unchanged:
poses are ``pose6 = [x, y, z (m), rx, ry, rz (rotation vector, rad)]``, joints are rad, linear
speeds m/s and accelerations m/s^2, joint speeds rad/s. Every command validates its input and
raises a typed :class:`EngineError` BEFORE anything moves; accepted commands return at once
and are executed by the thread.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Sequence

import numpy as np

from estimator.transforms import T_from_ur_pose, ur_pose_from_T
from fakes.ur_sim.arm_core import ArmCore
from fakes.ur_sim.command_api import CommandAPI
from fakes.ur_sim.commands import SafetyTrip
from fakes.ur_sim.cycle_loop import CycleLoop
from fakes.ur_sim.planning import MotionPlanner
from fakes.ur_sim.power import PowerControl
from fakes.ur_sim.safety import SafetySupervisor, check_joint_limits
from fakes.ur_sim.snapshots import SnapshotBuilder
from fakes.ur_sim.state import (
    CYCLE_S,
    HOME_Q_RAD,
    NUM_JOINTS,
    CommandOutcome,
    CommandRejectedError,
    EmergencyStopActiveError,
    EngineError,
    EngineSnapshot,
    FaultKind,
    NotRunningError,
    PathEntry,
    Pose6,
    ProtectiveStopActiveError,
    RobotMode,
    RobotStatusBit,
    SafetyMode,
    SafetyPlane,
    SafetyStatusBit,
    SimLimits,
    UnreachablePoseError,
    Vec,
    as_vector,
)

# The engine module is where callers import the simulator's types from.
__all__ = [
    "CYCLE_S",
    "HOME_Q_RAD",
    "CommandOutcome",
    "CommandRejectedError",
    "EmergencyStopActiveError",
    "EngineError",
    "EngineSnapshot",
    "MotionEngine",
    "NotRunningError",
    "PathEntry",
    "ProtectiveStopActiveError",
    "RobotMode",
    "RobotStatusBit",
    "SafetyMode",
    "SafetyPlane",
    "SafetyStatusBit",
    "SimLimits",
    "UnreachablePoseError",
]


class MotionEngine(CommandAPI):
    """A simulated UR5e arm moving in real time. All public methods are thread-safe.

    The motion commands (moves, speeds, servo, stops) are inherited from :class:`CommandAPI`;
    this class adds the controller around them: lifecycle and clock, state and history,
    power and safety (the dashboard's part) and the kinematics queries.
    """

    def __init__(
        self, q_rad: Sequence[float] | None = None, limits: SimLimits | None = None,
        autostart: bool = True,
    ) -> None:
        """Start in POWER_OFF at ``q_rad`` (default: home, tool pointing down)."""
        self.limits = limits or SimLimits()
        q = as_vector(HOME_Q_RAD if q_rad is None else q_rad, NUM_JOINTS, "q_rad")
        check_joint_limits(q, self.limits, "start q")
        core = ArmCore(q, self.limits)
        safety = SafetySupervisor(core)
        super().__init__(core, safety, MotionPlanner(core, safety))
        self._power = PowerControl(core, safety)
        self._snapshots = SnapshotBuilder(core)
        self._loop = CycleLoop(core, self._power.run_timers, self._step)
        self.contact_planes: tuple[SafetyPlane, ...] = ()
        if autostart:
            self.start()

    # -- lifecycle ----------------------------------------------------------------------
    def start(self) -> None:
        """Start the stepping thread (done by the constructor unless autostart=False)."""
        self._loop.start()

    def close(self) -> None:
        """Stop the thread; the engine is unusable afterwards."""
        self._loop.close()

    @property
    def alive(self) -> bool:
        """False once :meth:`close` was called (the "controller" is gone)."""
        return self._core.alive

    def __enter__(self) -> MotionEngine:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # -- the real-time loop -------------------------------------------------------------------
    def set_cycle_hook(self, hook: Callable[[], None] | None,
                       wants_cycles: Callable[[], bool] | None = None,
                       idle_period_s: float = 0.02) -> None:
        """Run ``hook`` after every controller cycle, on the engine thread, outside the lock.

        The protocol layer (control program, RTDE output) lives in this hook, so it steps on
        the same controller clock as the arm: after a host stall every missed cycle is run,
        in order, with its own timestamp. ``wants_cycles`` says whether somebody needs every
        cycle (an RTDE stream); otherwise the idle engine calls the hook every
        ``idle_period_s``.
        """
        with self._cond:
            self._core.hook = hook
            self._core.hook_wants = wants_cycles
            self._core.idle_period_s = idle_period_s
            self._cond.notify_all()

    @property
    def skipped_cycles(self) -> int:
        """Cycles lost to host stalls longer than the catch-up window."""
        return self._core.clock.skipped_cycles

    def controller_time_s(self) -> float:
        """Seconds since controller start on the controller's own 500 Hz clock."""
        with self._cond:
            self._core.sync_idle_clock()
            return self._core.clock.cycles * CYCLE_S

    def lag_s(self) -> float:
        """How far the controller clock is behind the host clock (0 when keeping up)."""
        with self._cond:
            self._core.sync_idle_clock()
            return max(0.0, time.monotonic() - self._core.now())

    def _step(self, now: float, dt: float) -> None:
        """One cycle of the active command; its result is applied only if it breaks no
        run-time limit (lock held, called by the cycle thread)."""
        core = self._core
        cmd = core.cmd
        assert cmd is not None
        try:
            out = cmd.step(core.step_context(), now, dt)
        except SafetyTrip as trip:
            self._safety.protective_stop(str(trip), now)
            return
        if cmd.limited:
            violation = self._safety.violation(out.q, out.qd)
            if violation:
                self._safety.protective_stop(violation, now)
                return
        core.q, core.qd, core.qdd = out.q, out.qd, out.qdd
        core.history.append((now, core.q.copy()))
        if out.done:
            # Every command ends at rest; finite-difference velocities of the last cycle aren't.
            core.qd, core.qdd = np.zeros(6), np.zeros(6)
            if cmd.name == "emergency_stop":  # category 1: power goes once the arm is at rest
                core.robot_mode = RobotMode.POWER_OFF
            core.finish(CommandOutcome.SUCCEEDED)

    # -- the simulated world and the safety limits -------------------------------------------
    def set_contact_planes(self, planes: Sequence[SafetyPlane]) -> None:
        """Surfaces in the simulated world the tool can touch (moveUntilContact); the free
        side is where ``normal . p >= offset_m``. No collision physics: contact is detected
        when the TCP reaches a surface, and nothing stops the arm but the program."""
        with self._cond:
            self.contact_planes = tuple(planes)

    def contact_excess_m(self, pose6: Sequence[float]) -> float:
        """How far (m) a TCP position is into the nearest contact surface (< 0: free)."""
        p = [float(v) for v in pose6[:3]]
        return max((pl.excess_m(p) for pl in self.contact_planes), default=-math.inf)

    def joints_within_safety_limits(self, q_rad: Sequence[float]) -> bool:
        """isJointsWithinSafetyLimits: inside the joint limits and the TCP on the allowed
        side of every safety plane."""
        q = as_vector(q_rad, 6, "q")
        if np.any(q < self.limits.joint_min_rad) or np.any(q > self.limits.joint_max_rad):
            return False
        with self._cond:
            return self._safety.workspace_excess_m(self._core.kin.forward_tcp(q)) <= 0

    def pose_within_safety_limits(self, pose6: Sequence[float]) -> bool:
        """isPoseWithinSafetyLimits: reachable inside the joint limits and the planes."""
        p = as_vector(pose6, 6, "pose")
        with self._cond:
            try:
                q = self._core.ik(p, self._core.q)
            except UnreachablePoseError:
                return False
        return self.joints_within_safety_limits(q.tolist())

    # -- state ---------------------------------------------------------------------------
    def snapshot(self) -> EngineSnapshot:
        with self._cond:
            return self._snapshots.snapshot()

    def wait_until_idle(self, timeout_s: float) -> bool:
        """Block until no command is active (also not braking); False on timeout."""
        with self._cond:
            return self._cond.wait_for(lambda: self._core.cmd is None, timeout=timeout_s)

    def outcome(self, command_id: int) -> CommandOutcome:
        """What became of the command with this id (KeyError for an unknown id)."""
        with self._cond:
            return self._core.outcomes[command_id]

    def wait_for(self, command_id: int, timeout_s: float) -> CommandOutcome:
        """Block until the command is no longer RUNNING (or timeout); returns its outcome."""
        with self._cond:
            self._cond.wait_for(
                lambda: self._core.outcomes[command_id] != CommandOutcome.RUNNING,
                timeout=timeout_s)
            return self._core.outcomes[command_id]

    def joints_at(self, host_monotonic_s: float) -> Vec:
        """Joint positions at a past ``time.monotonic()`` instant, interpolated from the
        stepping history (last 10 s). LookupError outside the history or in the future."""
        with self._cond:
            now = time.monotonic()
            hist = self._core.history
            if host_monotonic_s < hist[0][0] or host_monotonic_s > now + 1e-6:
                raise LookupError(f"t={host_monotonic_s:.3f} is outside the pose history")
            if host_monotonic_s >= hist[-1][0]:
                return hist[-1][1].copy()  # nothing has moved since the last step
            lo, hi = 0, len(hist) - 1
            while hi - lo > 1:
                mid = (lo + hi) // 2
                if hist[mid][0] <= host_monotonic_s:
                    lo = mid
                else:
                    hi = mid
            (ta, qa), (tb, qb) = hist[lo], hist[hi]
            w = (host_monotonic_s - ta) / (tb - ta) if tb > ta else 1.0
            return qa + w * (qb - qa)

    # -- power and safety (dashboard) --------------------------------------------------------
    def power_on(self) -> None:
        """POWER_OFF -> POWER_ON -> IDLE after ``limits.power_on_s``. Refused under e-stop."""
        with self._cond:
            self._power.power_on()

    def power_off(self) -> None:
        """Brakes on at once (any motion ends where it is) -> POWER_OFF."""
        with self._cond:
            self._power.power_off()

    def brake_release(self) -> None:
        """Release the brakes: (POWER_OFF ->) POWER_ON -> IDLE -> RUNNING, taking a moment."""
        with self._cond:
            self._power.brake_release()

    def unlock_protective_stop(self) -> bool:
        """Clear a protective stop. False (refused) within ``unlock_delay_s`` of the stop."""
        with self._cond:
            return self._safety.unlock_protective_stop()

    def trigger_protective_stop(self, reason: str = "triggered") -> None:
        """Brake quickly, abort the active command, refuse motion until unlocked."""
        with self._cond:
            self._safety.trigger_protective_stop(reason)

    def trigger_emergency_stop(self) -> None:
        """Category-1 stop: brake, then power off; ROBOT_EMERGENCY_STOP until released."""
        with self._cond:
            self._safety.emergency_stop()

    def release_emergency_stop(self) -> None:
        """E-stop button released: safety NORMAL, the arm stays POWER_OFF."""
        with self._cond:
            self._safety.release_emergency_stop()

    def inject(self, fault: FaultKind, after_s: float = 0.0) -> None:
        """Schedule a fault ``after_s`` from now (e.g. mid-move) for tests."""
        with self._cond:
            self._power.inject(fault, after_s)

    def set_speed_fraction(self, fraction: float) -> None:
        """The speed slider (0..1): profiled moves run slower in time, same path."""
        f = float(fraction)
        if not (math.isfinite(f) and 0.0 <= f <= 1.0):
            raise CommandRejectedError(f"speed fraction must be in [0, 1], got {fraction!r}")
        with self._cond:
            self._core.speed_fraction = f

    def set_program_running(self, running: bool) -> None:
        """The protocol layer's control script state, reported in ``robot_status_bits``."""
        with self._cond:
            self._core.program_running = bool(running)

    # -- kinematics -------------------------------------------------------------------------
    def set_tcp(self, pose6: Sequence[float]) -> None:
        """TCP offset in the flange frame (pose6). Refused while a command is active."""
        p = as_vector(pose6, 6, "TCP pose")
        with self._cond:
            if self._core.cmd is not None:
                raise CommandRejectedError("cannot change the TCP while the arm moves")
            self._core.kin.set_tcp(T_from_ur_pose(p.tolist()))
            self._core.tcp_offset = [float(v) for v in p]

    def fk(self, q_rad: Sequence[float]) -> Pose6:
        """TCP pose6 of a joint vector, with the current TCP offset."""
        q = as_vector(q_rad, 6, "q")
        with self._cond:
            return ur_pose_from_T(self._core.kin.forward_tcp(q))

    def ik(self, pose6: Sequence[float], q_near: Sequence[float] | None = None) -> list[float]:
        """Joints reaching the TCP pose6 nearest ``q_near`` (default: current q)."""
        p = as_vector(pose6, 6, "pose")
        with self._cond:
            seed = self._core.q if q_near is None else as_vector(q_near, 6, "q_near")
            return [float(v) for v in self._core.ik(p, seed)]
