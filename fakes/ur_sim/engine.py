"""The physical half of the simulated UR e-Series controller: a real-time motion engine.

The protocol servers (RTDE, script mailbox, dashboard) in ``fakes.ur_controller`` and the
in-process :class:`fakes.sim_arm.SimArm` both drive this one engine, so every client sees the
same arm. A background thread steps the arm at 500 Hz of wall-clock time (``time.monotonic``):
moves take the time their velocity profile says, a client that stops streaming servo/speed
commands sees the arm brake, and safety limits trip protective stops the way a controller's
safety system does. When nothing moves the thread sleeps on a condition, so an idle engine
costs next to no CPU on a shared machine.

Units at this API are UR's wire units so the protocol layer can pass values through unchanged:
poses are ``pose6 = [x, y, z (m), rx, ry, rz (rotation vector, rad)]``, joints are rad, linear
speeds m/s and accelerations m/s^2, joint speeds rad/s. Every command validates its input and
raises a typed :class:`EngineError` BEFORE anything moves; accepted commands return at once
and are executed by the thread.
"""

from __future__ import annotations

import logging
import math
import threading
import time
from collections import deque
from collections.abc import Callable, Sequence

import numpy as np

from estimator.transforms import T_from_ur_pose, ur_pose_from_T
from fakes.ur_sim.commands import (
    Brake,
    Command,
    MoveJ,
    MoveL,
    PathMove,
    SafetyTrip,
    Servo,
    SpeedJ,
    SpeedL,
    Then,
)
from fakes.ur_sim.kinematics import UnreachableError, UR5eKinematics
from fakes.ur_sim.profiles import BlendedLinearPath, JointProfile, LinearProfile
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
    JogFeature,
    NotRunningError,
    PathEntry,
    PathKind,
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
    positive_number,
)
from fakes.ur_sim.step_context import StepContext

Floats = tuple[float, ...]  # a pose or twist as a snapshot carries it

# The engine module is where callers import the simulator's types from.
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
    "RobotStatusBit",
    "SafetyMode",
    "SafetyPlane",
    "SafetyStatusBit",
    "SimLimits",
    "UnreachablePoseError",
]


_JOINT_RUNNING, _JOINT_IDLE, _JOINT_POWER_OFF = 253, 255, 239
_LIMIT_MARGIN = 1.02  # profiles ride exactly at the limit; only real excess trips a stop
_PATH_SAMPLE_MM = 5.0  # movel paths are checked through IK at least this densely
_PATH_SAMPLE_RAD = 0.05
_MAX_PATH_JOINT_STEP_RAD = 0.35  # a bigger jump between samples means a configuration flip
_HISTORY_S = 10.0
_MAX_CATCH_UP_CYCLES = 500  # a host stall up to 1 s is caught up cycle by cycle
log = logging.getLogger(__name__)

_SAFETY_BITS = {
    SafetyMode.NORMAL: (SafetyStatusBit.NORMAL_MODE,),
    SafetyMode.REDUCED: (SafetyStatusBit.REDUCED_MODE,),
    SafetyMode.PROTECTIVE_STOP: (SafetyStatusBit.PROTECTIVE_STOPPED,
                                 SafetyStatusBit.STOPPED_DUE_TO_SAFETY),
    SafetyMode.RECOVERY: (SafetyStatusBit.RECOVERY_MODE,),
    SafetyMode.SAFEGUARD_STOP: (SafetyStatusBit.SAFEGUARD_STOPPED,
                                SafetyStatusBit.STOPPED_DUE_TO_SAFETY),
    SafetyMode.SYSTEM_EMERGENCY_STOP: (SafetyStatusBit.SYSTEM_EMERGENCY_STOPPED,
                                       SafetyStatusBit.EMERGENCY_STOPPED,
                                       SafetyStatusBit.STOPPED_DUE_TO_SAFETY),
    SafetyMode.ROBOT_EMERGENCY_STOP: (SafetyStatusBit.ROBOT_EMERGENCY_STOPPED,
                                      SafetyStatusBit.EMERGENCY_STOPPED,
                                      SafetyStatusBit.STOPPED_DUE_TO_SAFETY),
    SafetyMode.VIOLATION: (SafetyStatusBit.VIOLATION, SafetyStatusBit.STOPPED_DUE_TO_SAFETY),
    SafetyMode.FAULT: (SafetyStatusBit.FAULT, SafetyStatusBit.STOPPED_DUE_TO_SAFETY),
}
_ESTOP = (SafetyMode.ROBOT_EMERGENCY_STOP, SafetyMode.SYSTEM_EMERGENCY_STOP)
_POWERED = (RobotMode.POWER_ON, RobotMode.IDLE, RobotMode.RUNNING)


class MotionEngine:
    """A simulated UR5e arm moving in real time. All public methods are thread-safe."""

    def __init__(
        self, q_rad: Sequence[float] | None = None, limits: SimLimits | None = None,
        autostart: bool = True,
    ) -> None:
        """Start in POWER_OFF at ``q_rad`` (default: home, tool pointing down)."""
        self.limits = limits or SimLimits()
        self._kin = UR5eKinematics(joint_min_rad=self.limits.joint_min_rad,
                                   joint_max_rad=self.limits.joint_max_rad)
        self._cond = threading.Condition()
        self._q = as_vector(HOME_Q_RAD if q_rad is None else q_rad, NUM_JOINTS, "q_rad")
        self._check_joint_limits(self._q, "start q")
        self._qd = np.zeros(6)
        self._qdd = np.zeros(6)
        self._tcp_offset: Pose6 = [0.0] * 6
        self._robot_mode = RobotMode.POWER_OFF
        self._safety_mode = SafetyMode.NORMAL
        self._stop_t: float | None = None
        self._stop_reason = ""
        self._program_running = False
        self._speed_fraction = 1.0
        self._cmd: Command | None = None
        self._next_id = 1
        self._outcomes: dict[int, CommandOutcome] = {}
        self._timers: list[tuple[float, str]] = []  # (due monotonic, event)
        self._t0 = time.monotonic()
        self._cycles = 0  # controller cycles since t0: the controller's own clock
        self.skipped_cycles = 0  # cycles lost to host stalls longer than the catch-up window
        self._hook: Callable[[], None] | None = None
        self._servo_ik: tuple[Vec, Vec] | None = None  # last servol pose and its IK
        self._snap_cache: tuple[tuple[object, ...], EngineSnapshot] | None = None
        # (joints, speeds, TCP offset) -> TCP pose and speed (see _tcp_state)
        self._tcp_cache: tuple[tuple[object, ...], Floats, Floats] | None = None
        self.contact_planes: tuple[SafetyPlane, ...] = ()
        self._hook_wants: Callable[[], bool] | None = None
        self._idle_period_s = 0.02
        self._history: deque[tuple[float, Vec]] = deque(maxlen=int(_HISTORY_S / CYCLE_S))
        self._history.append((self._t0, self._q.copy()))
        self._alive = True
        self._thread: threading.Thread | None = None
        if autostart:
            self.start()

    # -- lifecycle ----------------------------------------------------------------------
    def start(self) -> None:
        """Start the stepping thread (done by the constructor unless autostart=False)."""
        with self._cond:
            if self._thread is not None:
                return
            self._thread = threading.Thread(target=self._run, name="ur-sim-engine", daemon=True)
            self._thread.start()

    def close(self) -> None:
        """Stop the thread; the engine is unusable afterwards."""
        with self._cond:
            self._alive = False
            self._cond.notify_all()
        if self._thread is not None and self._thread is not threading.current_thread():
            self._thread.join(timeout=2.0)

    @property
    def alive(self) -> bool:
        """False once :meth:`close` was called (the "controller" is gone)."""
        return self._alive

    def __enter__(self) -> MotionEngine:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # -- the real-time loop -------------------------------------------------------------------
    def _busy(self) -> bool:
        return self._cmd is not None

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
            self._hook = hook
            self._hook_wants = wants_cycles
            self._idle_period_s = idle_period_s
            self._cond.notify_all()

    def _cycling(self) -> bool:
        wants = self._hook_wants
        return self._busy() or (self._hook is not None and wants is not None and wants())

    def _now(self) -> float:
        """The controller clock, as a ``time.monotonic()`` instant: t0 + cycles * 2 ms."""
        return self._t0 + self._cycles * CYCLE_S

    def _sync_idle_clock(self) -> None:
        """An idle controller's clock is simply the present (no cycle to catch up)."""
        if not self._cycling():
            due = int((time.monotonic() - self._t0) / CYCLE_S)
            self._cycles = max(self._cycles, due)

    def controller_time_s(self) -> float:
        """Seconds since controller start on the controller's own 500 Hz clock."""
        with self._cond:
            self._sync_idle_clock()
            return self._cycles * CYCLE_S

    def lag_s(self) -> float:
        """How far the controller clock is behind the host clock (0 when keeping up)."""
        with self._cond:
            self._sync_idle_clock()
            return max(0.0, time.monotonic() - self._now())

    def _run(self) -> None:
        while True:
            with self._cond:
                if not self._alive:
                    return
                due = int((time.monotonic() - self._t0) / CYCLE_S)
                if not self._cycling():
                    self._cycles = max(self._cycles, due)
                    self._run_timers(self._now())
                    if not self._cycling():
                        period = self._idle_period_s if self._hook is not None else 1.0
                        wake = min((t for t, _ in self._timers),
                                   default=time.monotonic() + period)
                        self._cond.wait(timeout=max(0.0, min(wake - time.monotonic(), period)))
                        hook = self._hook if self._alive and not self._cycling() else None
                        if hook is None:
                            continue
                    else:
                        hook = None
                else:
                    hook = None
            if hook is not None:
                self._call_hook(hook)
                continue
            self._cycle_until(due)

    def _cycle_until(self, due: int) -> None:
        """Run controller cycles up to ``due`` (catching up after a stall), then wait for the
        next one. A stall longer than ``_MAX_CATCH_UP_S`` is skipped, and the skip is visible
        as a jump in the controller clock (RTDE ``timestamp``), as a real gap would be."""
        behind = due - self._cycles
        if behind > _MAX_CATCH_UP_CYCLES:
            with self._cond:
                self._cycles = due - _MAX_CATCH_UP_CYCLES
                self.skipped_cycles += behind - _MAX_CATCH_UP_CYCLES
        while self._alive:
            with self._cond:
                if self._cycles >= due or not self._cycling():
                    break
                self._cycles += 1
                now = self._now()
                self._run_timers(now)
                if self._busy():
                    self._step(now, CYCLE_S)
                hook = self._hook
            if hook is not None:
                self._call_hook(hook)
        delay = self._t0 + (self._cycles + 1) * CYCLE_S - time.monotonic()
        if delay > 0:
            time.sleep(delay)

    def _call_hook(self, hook: Callable[[], None]) -> None:
        try:
            hook()
        except Exception:  # the controller cycle must survive anything one step does
            log.exception("controller cycle hook failed")

    def _run_timers(self, now: float) -> None:
        due = [e for t, e in self._timers if t <= now]
        if not due:
            return
        self._timers = [(t, e) for t, e in self._timers if t > now]
        for event in due:
            if event == "idle" and self._robot_mode == RobotMode.POWER_ON:
                self._robot_mode = RobotMode.IDLE
            elif event == "running" and self._robot_mode in (RobotMode.POWER_ON, RobotMode.IDLE):
                self._robot_mode = RobotMode.RUNNING
            elif event == "protective_stop":
                self._protective_stop("injected protective stop", now)
            elif event == "emergency_stop":
                self._emergency_stop()
        self._cond.notify_all()

    def _step(self, now: float, dt: float) -> None:
        cmd = self._cmd
        assert cmd is not None
        try:
            out = cmd.step(self._step_context(), now, dt)
        except SafetyTrip as trip:
            self._protective_stop(str(trip), now)
            return
        if cmd.limited:
            violation = self._violation(out.q, out.qd)
            if violation:
                self._protective_stop(violation, now)
                return
        self._q, self._qd, self._qdd = out.q, out.qd, out.qdd
        self._history.append((now, self._q.copy()))
        if out.done:
            # Every command ends at rest; finite-difference velocities of the last cycle aren't.
            self._qd, self._qdd = np.zeros(6), np.zeros(6)
            if cmd.name == "emergency_stop":  # category 1: power goes once the arm is at rest
                self._robot_mode = RobotMode.POWER_OFF
            self._finish(CommandOutcome.SUCCEEDED)

    def _step_context(self) -> StepContext:
        return StepContext(self._q, self._qd, self._speed_fraction, self._kin, self.limits)

    def _violation(self, q: Vec, qd: Vec) -> str:
        lim = self.limits
        if np.any(q < lim.joint_min_rad - 1e-9) or np.any(q > lim.joint_max_rad + 1e-9):
            return "joint position limit"
        if float(np.max(np.abs(qd))) > lim.max_joint_speed_rad_s * _LIMIT_MARGIN:
            return "joint speed limit"
        T_tcp, J = self._kin.tcp_and_jacobian(q)
        tcp_speed = float(np.linalg.norm((J @ qd)[:3])) / 1000.0
        if tcp_speed > lim.max_tcp_speed_m_s * _LIMIT_MARGIN:
            return f"tool speed limit ({tcp_speed:.2f} m/s)"
        outside = self._workspace_excess_m(T_tcp)
        if outside > 0 and outside > self._workspace_excess_m(self._kin.forward_tcp(self._q)):
            return "TCP crossed a safety plane"  # (moving back to the allowed side is allowed)
        return ""

    def _workspace_excess_m(self, T_base_tcp: Vec) -> float:
        """How far (m) the TCP is beyond the worst safety plane (<= 0: on the allowed side)."""
        p = T_base_tcp[:3, 3] / 1000.0
        return max((pl.excess_m(p) for pl in self.limits.safety_planes), default=-math.inf)

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
            return self._workspace_excess_m(self._kin.forward_tcp(q)) <= 0

    def pose_within_safety_limits(self, pose6: Sequence[float]) -> bool:
        """isPoseWithinSafetyLimits: reachable inside the joint limits and the planes."""
        p = as_vector(pose6, 6, "pose")
        with self._cond:
            try:
                q = self._ik_locked(p, self._q)
            except UnreachablePoseError:
                return False
        return self.joints_within_safety_limits(q.tolist())

    def _finish(self, outcome: CommandOutcome, then: Command | None = None) -> None:
        if self._cmd is not None and self._outcomes.get(self._cmd.id) == CommandOutcome.RUNNING:
            self._outcomes[self._cmd.id] = outcome
        self._cmd = then
        self._cond.notify_all()

    def _protective_stop(self, reason: str, now: float) -> None:
        self._safety_mode = SafetyMode.PROTECTIVE_STOP
        self._stop_t = now
        self._stop_reason = reason
        self._brake_now(self.limits.protective_stop_decel_rad_s2, "protective_stop",
                        CommandOutcome.ABORTED)

    def _emergency_stop(self) -> None:
        self._safety_mode = SafetyMode.ROBOT_EMERGENCY_STOP
        self._stop_reason = "emergency stop"
        self._timers = []
        self._brake_now(self.limits.protective_stop_decel_rad_s2, "emergency_stop",
                        CommandOutcome.ABORTED)
        if self._cmd is None:
            self._robot_mode = RobotMode.POWER_OFF

    def _brake_now(self, decel: float, name: str, outcome: CommandOutcome) -> None:
        """End the active command, braking from the present velocity."""
        brake = Brake(0, name, self._q, self._qd, decel)
        self._finish(outcome, brake if brake.T > 0 else None)
        if self._cmd is None:
            self._qd = np.zeros(6)
            self._qdd = np.zeros(6)
        self._cond.notify_all()

    # -- state ---------------------------------------------------------------------------
    def snapshot(self) -> EngineSnapshot:
        with self._cond:
            return self._snapshot_locked()

    def _snapshot_locked(self) -> EngineSnapshot:
        # While moving, the state belongs to the last control cycle, not to the reading instant.
        self._sync_idle_clock()
        # One snapshot per cycle and state: the protocol layer asks several times a cycle.
        key = (self._cycles, self._next_id, id(self._cmd), self._safety_mode, self._robot_mode,
               self._program_running, self._speed_fraction, tuple(self._tcp_offset),
               self._stop_reason, self._q.tobytes(), self._qd.tobytes())
        if self._snap_cache is not None and self._snap_cache[0] == key:
            return self._snap_cache[1]
        snap = self._build_snapshot()
        self._snap_cache = (key, snap)
        return snap

    def _tcp_state(self, q: Vec, qd: Vec) -> tuple[Floats, Floats]:
        """TCP pose (UR) and speed of joints ``q``, ``qd``: the kinematics are most of a
        cycle's cost, so a standing arm's are computed once, not 500 times a second."""
        key = (q.tobytes(), qd.tobytes(), tuple(self._tcp_offset))
        cached = self._tcp_cache
        if cached is not None and cached[0] == key:
            return cached[1], cached[2]
        pose = tuple(map(float, ur_pose_from_T(self._kin.forward_tcp(q))))
        twist = self._kin.jacobian_tcp(q) @ qd
        twist[:3] /= 1000.0
        speed = tuple(map(float, twist))
        self._tcp_cache = (key, pose, speed)
        return pose, speed

    def _build_snapshot(self) -> EngineSnapshot:
        now = self._now()
        q, qd = self._q, self._qd
        pose, twist = self._tcp_state(q, qd)
        safety = self._safety_mode
        sbits = sum(1 << int(b) for b in _SAFETY_BITS[safety])
        rbits = (1 << RobotStatusBit.POWER_ON) if self._robot_mode in _POWERED else 0
        if self._program_running:
            rbits |= 1 << RobotStatusBit.PROGRAM_RUNNING
        mode = self._robot_mode
        joint_mode = (_JOINT_RUNNING if mode == RobotMode.RUNNING
                      else _JOINT_IDLE if mode in _POWERED else _JOINT_POWER_OFF)
        uptime = now - self._t0
        temps = tuple(25.0 + 8.0 * (1.0 - math.exp(-uptime / 600.0)) + 0.5 * i
                      for i in range(6)) if mode in _POWERED else (25.0,) * 6
        cmd = self._cmd
        stopped = safety != SafetyMode.NORMAL
        return EngineSnapshot(
            timestamp_s=uptime,
            host_monotonic_s=now,
            q=tuple(map(float, q)),
            qd=tuple(map(float, qd)),
            target_q=tuple(map(float, q)),
            target_qd=tuple(map(float, qd)),
            target_qdd=tuple(map(float, self._qdd)),
            tcp_pose=pose,
            tcp_speed=twist,
            target_tcp_pose=pose,
            target_tcp_speed=twist,
            tcp_offset=tuple(self._tcp_offset),
            tcp_force=(0.0,) * 6,
            joint_temperatures_c=temps,
            actual_current_a=tuple(float(0.3 * a) for a in self._qdd),
            joint_modes=(joint_mode,) * 6,
            robot_mode=mode,
            safety_mode=safety,
            safety_status_bits=sbits,
            robot_status_bits=rbits,
            moving=bool(cmd is not None or np.any(qd)),
            active_command=cmd.name if cmd is not None else None,
            async_progress=cmd.progress if cmd is not None else -1,
            speed_scaling=0.0 if stopped else self._speed_fraction,
            target_speed_fraction=self._speed_fraction,
            seconds_since_protective_stop=(
                now - self._stop_t if safety == SafetyMode.PROTECTIVE_STOP
                and self._stop_t is not None else None),
            last_stop_reason=self._stop_reason,
            last_command_id=self._next_id - 1,
        )

    def wait_until_idle(self, timeout_s: float) -> bool:
        """Block until no command is active (also not braking); False on timeout."""
        with self._cond:
            return self._cond.wait_for(lambda: self._cmd is None, timeout=timeout_s)

    def outcome(self, command_id: int) -> CommandOutcome:
        """What became of the command with this id (KeyError for an unknown id)."""
        with self._cond:
            return self._outcomes[command_id]

    def wait_for(self, command_id: int, timeout_s: float) -> CommandOutcome:
        """Block until the command is no longer RUNNING (or timeout); returns its outcome."""
        with self._cond:
            self._cond.wait_for(
                lambda: self._outcomes[command_id] != CommandOutcome.RUNNING, timeout=timeout_s)
            return self._outcomes[command_id]

    def joints_at(self, host_monotonic_s: float) -> Vec:
        """Joint positions at a past ``time.monotonic()`` instant, interpolated from the
        stepping history (last 10 s). LookupError outside the history or in the future."""
        with self._cond:
            now = time.monotonic()
            hist = self._history
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
            if self._safety_mode in _ESTOP:
                raise EmergencyStopActiveError("release the emergency stop before powering on")
            if self._robot_mode == RobotMode.POWER_OFF:
                self._robot_mode = RobotMode.POWER_ON
                self._sync_idle_clock()
                self._timers.append((self._now() + self.limits.power_on_s, "idle"))
                self._cond.notify_all()

    def power_off(self) -> None:
        """Brakes on at once (any motion ends where it is) -> POWER_OFF."""
        with self._cond:
            self._finish(CommandOutcome.ABORTED)
            self._qd = np.zeros(6)
            self._qdd = np.zeros(6)
            self._timers = [(t, e) for t, e in self._timers if e not in ("idle", "running")]
            self._robot_mode = RobotMode.POWER_OFF
            self._cond.notify_all()

    def brake_release(self) -> None:
        """Release the brakes: (POWER_OFF ->) POWER_ON -> IDLE -> RUNNING, taking a moment."""
        with self._cond:
            if self._robot_mode == RobotMode.RUNNING:
                return
            self.power_on()
            idle_due = max([t for t, e in self._timers if e == "idle"],
                           default=self._now())
            self._timers.append((idle_due + self.limits.brake_release_s, "running"))
            self._cond.notify_all()

    def unlock_protective_stop(self) -> bool:
        """Clear a protective stop. False (refused) within ``unlock_delay_s`` of the stop."""
        with self._cond:
            if self._safety_mode != SafetyMode.PROTECTIVE_STOP:
                return self._safety_mode == SafetyMode.NORMAL
            assert self._stop_t is not None
            self._sync_idle_clock()
            if self._now() - self._stop_t < self.limits.unlock_delay_s:
                return False
            self._safety_mode = SafetyMode.NORMAL
            self._stop_t = None
            return True

    def trigger_protective_stop(self, reason: str = "triggered") -> None:
        """Brake quickly, abort the active command, refuse motion until unlocked."""
        with self._cond:
            if self._safety_mode not in _ESTOP:
                self._protective_stop(reason, self._now())

    def trigger_emergency_stop(self) -> None:
        """Category-1 stop: brake, then power off; ROBOT_EMERGENCY_STOP until released."""
        with self._cond:
            self._emergency_stop()

    def release_emergency_stop(self) -> None:
        """E-stop button released: safety NORMAL, the arm stays POWER_OFF."""
        with self._cond:
            if self._safety_mode in _ESTOP:
                self._safety_mode = SafetyMode.NORMAL
                self._stop_t = None

    def inject(self, fault: FaultKind, after_s: float = 0.0) -> None:
        """Schedule a fault ``after_s`` from now (e.g. mid-move) for tests."""
        if fault not in ("protective_stop", "emergency_stop"):
            raise CommandRejectedError(f"unknown fault {fault!r}")
        with self._cond:
            self._sync_idle_clock()
            self._timers.append((self._now() + max(0.0, float(after_s)), fault))
            self._cond.notify_all()

    def set_speed_fraction(self, fraction: float) -> None:
        """The speed slider (0..1): profiled moves run slower in time, same path."""
        f = float(fraction)
        if not (math.isfinite(f) and 0.0 <= f <= 1.0):
            raise CommandRejectedError(f"speed fraction must be in [0, 1], got {fraction!r}")
        with self._cond:
            self._speed_fraction = f

    def set_program_running(self, running: bool) -> None:
        """The protocol layer's control script state, reported in ``robot_status_bits``."""
        with self._cond:
            self._program_running = bool(running)

    # -- kinematics -------------------------------------------------------------------------
    def set_tcp(self, pose6: Sequence[float]) -> None:
        """TCP offset in the flange frame (pose6). Refused while a command is active."""
        p = as_vector(pose6, 6, "TCP pose")
        with self._cond:
            if self._cmd is not None:
                raise CommandRejectedError("cannot change the TCP while the arm moves")
            self._kin.set_tcp(T_from_ur_pose(p.tolist()))
            self._tcp_offset = [float(v) for v in p]

    def fk(self, q_rad: Sequence[float]) -> Pose6:
        """TCP pose6 of a joint vector, with the current TCP offset."""
        q = as_vector(q_rad, 6, "q")
        with self._cond:
            return ur_pose_from_T(self._kin.forward_tcp(q))

    def ik(self, pose6: Sequence[float], q_near: Sequence[float] | None = None) -> list[float]:
        """Joints reaching the TCP pose6 nearest ``q_near`` (default: current q)."""
        p = as_vector(pose6, 6, "pose")
        with self._cond:
            seed = self._q if q_near is None else as_vector(q_near, 6, "q_near")
            return [float(v) for v in self._ik_locked(p, seed)]

    def _ik_locked(self, pose6: Vec, seed: Vec) -> Vec:
        try:
            return self._kin.inverse_tcp(T_from_ur_pose(pose6.tolist()), seed)
        except UnreachableError as err:
            raise UnreachablePoseError(f"pose {list(pose6)} is unreachable: {err}") from err

    # -- command plumbing ----------------------------------------------------------------------
    def _check_joint_limits(self, q: Vec, what: str) -> None:
        if np.any(q < self.limits.joint_min_rad) or np.any(q > self.limits.joint_max_rad):
            raise CommandRejectedError(
                f"{what} {np.round(q, 4).tolist()} is outside the joint limits "
                f"[{self.limits.joint_min_rad:.4f}, {self.limits.joint_max_rad:.4f}] rad")

    def _require_motion_allowed(self) -> None:
        self._sync_idle_clock()
        if self._safety_mode in _ESTOP:
            raise EmergencyStopActiveError("the arm is emergency-stopped")
        if self._safety_mode == SafetyMode.PROTECTIVE_STOP:
            raise ProtectiveStopActiveError(
                f"the arm is protective-stopped ({self._stop_reason}); unlock it first")
        if self._safety_mode != SafetyMode.NORMAL:
            raise NotRunningError(f"safety mode is {self._safety_mode.name}")
        if self._robot_mode != RobotMode.RUNNING:
            raise NotRunningError(f"robot mode is {self._robot_mode.name}, not RUNNING")

    def _trip(self, reason: str) -> None:
        """A command that would break a safety limit: stop the arm and refuse the command."""
        self._protective_stop(reason, self._now())
        raise ProtectiveStopActiveError(f"protective stop: {reason}")

    def _new_id(self) -> int:
        """The id the next installed command gets; consumed only by :meth:`_install`, so a
        rejected command leaves no trace."""
        return self._next_id

    def _rest_start(self, accel: float) -> tuple[Vec, Brake | None]:
        """Where a profiled move will start: here, or where the present motion brakes to."""
        if self._cmd is None and not np.any(self._qd):
            return self._q.copy(), None
        brake = Brake(0, "brake", self._q, self._qd, max(accel, 1.0))
        return brake.q_end, brake

    def _install(self, cmd: Command, brake: Brake | None = None) -> int:
        self._finish(CommandOutcome.PREEMPTED)
        self._next_id = cmd.id + 1
        self._outcomes[cmd.id] = CommandOutcome.RUNNING
        if len(self._outcomes) > 1000:
            for old in sorted(self._outcomes)[:500]:
                del self._outcomes[old]
        self._cmd = Then(brake, cmd) if brake is not None and brake.T > 0 else cmd
        self._cond.notify_all()
        return cmd.id

    def _plan_j(self, q0: Vec, q1: Vec, speed: float, accel: float, cid: int, name: str
                ) -> MoveJ:
        self._check_joint_limits(q1, "target")
        return MoveJ(cid, name, JointProfile(q0, q1, speed, accel))

    def _plan_l(self, q0: Vec, pose6: Vec, speed: float, accel: float
                ) -> tuple[LinearProfile, Vec]:
        """Check the whole straight line through IK before accepting it; returns the end q."""
        if speed > self.limits.max_tcp_speed_m_s:
            self._trip(f"movel speed {speed:g} m/s exceeds the tool speed limit "
                       f"{self.limits.max_tcp_speed_m_s:g} m/s")
        T0 = self._kin.forward_tcp(q0)
        T1 = T_from_ur_pose(pose6.tolist())
        prof = LinearProfile(T0, T1, speed * 1000.0, accel * 1000.0, speed, accel)
        n = max(2, math.ceil(prof.length_mm / _PATH_SAMPLE_MM),
                math.ceil(prof.angle_rad / _PATH_SAMPLE_RAD))
        q = q0
        for u in np.linspace(0.0, 1.0, n + 1)[1:]:
            try:
                q_next = self._kin.inverse_tcp_local(prof.pose_at_progress(float(u)), q)
            except UnreachableError as err:
                raise UnreachablePoseError(
                    f"linear path to {list(pose6)} leaves the reachable workspace or the "
                    f"joint limits at {u:.0%} of the way") from err
            if float(np.max(np.abs(q_next - q))) > _MAX_PATH_JOINT_STEP_RAD:
                raise UnreachablePoseError(
                    f"linear path to {list(pose6)} passes through a singularity at {u:.0%}")
            q = q_next
        return prof, q

    # -- profiled moves ---------------------------------------------------------------------
    def move_j(self, q_rad: Sequence[float], speed_rad_s: float, accel_rad_s2: float) -> int:
        """Synchronised trapezoidal joint move; returns the command id."""
        q1 = as_vector(q_rad, 6, "target q")
        v = positive_number(speed_rad_s, "joint speed", self.limits.max_joint_speed_rad_s)
        a = positive_number(accel_rad_s2, "joint acceleration", self.limits.max_joint_accel_rad_s2)
        with self._cond:
            self._require_motion_allowed()
            q0, brake = self._rest_start(a)
            cmd = self._plan_j(q0, q1, v, a, self._new_id(), "movej")
            return self._install(cmd, brake)

    def move_j_ik(self, pose6: Sequence[float], speed_rad_s: float, accel_rad_s2: float) -> int:
        """Joint move to the IK solution of a TCP pose nearest the current q (URScript movej(p))."""
        p = as_vector(pose6, 6, "target pose")
        v = positive_number(speed_rad_s, "joint speed", self.limits.max_joint_speed_rad_s)
        a = positive_number(accel_rad_s2, "joint acceleration", self.limits.max_joint_accel_rad_s2)
        with self._cond:
            self._require_motion_allowed()
            q0, brake = self._rest_start(a)
            q1 = self._ik_locked(p, q0)
            cmd = self._plan_j(q0, q1, v, a, self._new_id(), "movej")
            return self._install(cmd, brake)

    def move_l(self, pose6: Sequence[float], speed_m_s: float, accel_m_s2: float) -> int:
        """Straight-line TCP move (orientation by slerp); returns the command id.

        The whole line is checked through inverse kinematics first (reach, joint limits,
        singularities). A speed above the tool speed limit trips a protective stop.
        """
        p = as_vector(pose6, 6, "target pose")
        v = positive_number(speed_m_s, "tool speed")
        a = positive_number(accel_m_s2, "tool acceleration", self.limits.max_tcp_accel_m_s2)
        with self._cond:
            self._require_motion_allowed()
            q0, brake = self._rest_start(a)
            prof, _ = self._plan_l(q0, p, v, a)
            return self._install(MoveL(self._new_id(), "movel", BlendedLinearPath([prof], [])),
                                 brake)

    def move_path(self, path: Sequence[PathEntry]) -> int:
        """Run waypoints in order; ``async_progress`` is the index of the entry under way.

        Consecutive ``movel`` entries with a blend radius (m, at most half of either
        neighbouring segment) round their corner without stopping; other corners are stop
        points. All segments are planned and checked before the arm moves.
        """
        if not path:
            raise CommandRejectedError("empty path")
        with self._cond:
            self._require_motion_allowed()
            cid = self._new_id()
            q, brake = self._rest_start(1.0)
            segments: list[Command] = []
            run: list[LinearProfile] = []  # movel profiles to be blended together
            run_blends: list[float] = []
            run_first = 0
            for i, entry in enumerate(path):
                kind, tgt, v, a, blend = self._path_entry(i, entry)
                if kind == "movej_pose":
                    tgt = self._ik_locked(tgt, q)
                elif kind == "movel_joints":
                    self._check_joint_limits(tgt, f"path entry {i} target")
                    tgt = np.asarray(ur_pose_from_T(self._kin.forward_tcp(tgt)))
                if kind in ("movej", "movej_pose"):
                    if run:
                        segments.append(self._blended(cid, run, run_blends[:-1], run_first))
                        run, run_blends = [], []
                    seg = self._plan_j(q, tgt, v, a, cid, "movej")
                    seg.progress = i
                    segments.append(seg)
                    q = tgt
                    continue
                prof, q = self._plan_l(q, tgt, v, a)
                if run and run_blends[-1] > 0:
                    limit_mm = 0.5 * min(run[-1].length_mm, prof.length_mm)
                    if run_blends[-1] > limit_mm + 1e-9:
                        raise CommandRejectedError(
                            f"path entry {i - 1}: blend {run_blends[-1] / 1000:g} m exceeds "
                            f"half of a neighbouring segment ({limit_mm / 1000:g} m)")
                    run.append(prof)
                else:
                    if run:
                        segments.append(self._blended(cid, run, run_blends[:-1], run_first))
                    run, run_blends, run_first = [prof], [], i
                nxt = path[i + 1][0] if i + 1 < len(path) else None
                run_blends.append(blend * 1000.0 if nxt in ("movel", "movel_joints") else 0.0)
            if run:
                segments.append(self._blended(cid, run, run_blends[:-1], run_first))
            return self._install(PathMove(cid, segments), brake)

    @staticmethod
    def _blended(cid: int, run: list[LinearProfile], blends_mm: list[float], first: int
                 ) -> MoveL:
        return MoveL(cid, "movel", BlendedLinearPath(run, blends_mm), first)

    def _path_entry(self, i: int, entry: PathEntry) -> tuple[PathKind, Vec, float, float, float]:
        try:
            kind, target, speed, accel, blend = entry
        except (TypeError, ValueError) as err:
            raise CommandRejectedError(
                f"path entry {i} must be (kind, target, speed, accel, blend)") from err
        b = float(blend)
        if not (math.isfinite(b) and b >= 0):
            raise CommandRejectedError(f"path entry {i}: blend must be >= 0")
        tgt = as_vector(target, 6, f"path entry {i} target")
        if kind in ("movej", "movej_pose"):
            v = positive_number(speed, f"path entry {i} speed", self.limits.max_joint_speed_rad_s)
            a = positive_number(accel, f"path entry {i} accel", self.limits.max_joint_accel_rad_s2)
        elif kind in ("movel", "movel_joints"):
            v = positive_number(speed, f"path entry {i} speed")
            a = positive_number(accel, f"path entry {i} accel", self.limits.max_tcp_accel_m_s2)
        else:
            raise CommandRejectedError(f"path entry {i}: unknown kind {kind!r}")
        return kind, tgt, v, a, b

    # -- streamed motion ---------------------------------------------------------------------
    def _expiry(self, time_s: float) -> float | None:
        t = float(time_s)
        if not math.isfinite(t):
            raise CommandRejectedError(f"time must be finite, got {time_s!r}")
        with self._cond:
            self._sync_idle_clock()
            return self._now() + t if t > 0 else None

    def speed_j(self, qd_rad_s: Sequence[float], accel_rad_s2: float, time_s: float = 0.0
                ) -> int:
        """Joint velocity. Brakes with ``accel`` when no new command arrives within ``time_s``
        (``time_s <= 0``: runs until :meth:`speed_stop` or another command)."""
        qd = as_vector(qd_rad_s, 6, "joint speeds")
        a = positive_number(accel_rad_s2, "joint acceleration", self.limits.max_joint_accel_rad_s2)
        expire = self._expiry(time_s)
        with self._cond:
            self._require_motion_allowed()
            if float(np.max(np.abs(qd))) > self.limits.max_joint_speed_rad_s:
                self._trip("speedj above the joint speed limit")
            cmd = SpeedJ(self._new_id(), self._qd, qd, a, expire)
            return self._install(cmd)

    def speed_l(self, xd: Sequence[float], accel_m_s2: float, time_s: float = 0.0) -> int:
        """Base-frame TCP twist ``[vx, vy, vz (m/s), wx, wy, wz (rad/s)]``; expiry as speed_j."""
        return self._speed_l("speedl", xd, "base", accel_m_s2, time_s)

    def jog_start(
        self, speeds6: Sequence[float], feature: JogFeature = "base", accel_m_s2: float = 0.5,
        time_s: float = 0.0,
    ) -> int:
        """Cartesian jog in base or tool frame until :meth:`jog_stop`; with ``time_s > 0`` it
        also brakes on its own when not re-sent within ``time_s`` (a client's watchdog)."""
        if feature not in ("base", "tool"):
            raise CommandRejectedError(f"jog feature must be 'base' or 'tool', got {feature!r}")
        return self._speed_l("jog", speeds6, feature, accel_m_s2, time_s)

    def _speed_l(self, name: str, xd: Sequence[float], frame: JogFeature, accel_m_s2: float,
                 time_s: float) -> int:
        twist = as_vector(xd, 6, "TCP speeds")
        a = positive_number(accel_m_s2, "tool acceleration", self.limits.max_tcp_accel_m_s2)
        expire = self._expiry(time_s)
        with self._cond:
            self._require_motion_allowed()
            if float(np.linalg.norm(twist[:3])) > self.limits.max_tcp_speed_m_s:
                self._trip(f"{name} above the tool speed limit")
            target = np.concatenate([twist[:3] * 1000.0, twist[3:]])
            cmd = SpeedL(self._new_id(), name, self._step_context(), target, frame, a * 1000.0, a,
                         expire)
            return self._install(cmd)

    def jog_stop(self, decel_m_s2: float = 0.5) -> None:
        self.speed_stop(decel_m_s2 if decel_m_s2 > 0 else 0.5)

    def servo_j(
        self, q_rad: Sequence[float], time_s: float = CYCLE_S, lookahead_s: float = 0.1,
        gain: float = 300.0,
    ) -> int:
        """Go to ``q`` within ``time_s``; the stream must keep coming (watchdog) or the arm
        brakes. ``lookahead_s`` and ``gain`` shape the tracking (see :class:`Servo`)."""
        q = as_vector(q_rad, 6, "servo target q")
        with self._cond:
            return self._servo("servoj", q, time_s, lookahead_s, gain)

    def servo_l(
        self, pose6: Sequence[float], time_s: float = CYCLE_S, lookahead_s: float = 0.1,
        gain: float = 300.0,
    ) -> int:
        """As :meth:`servo_j` with a TCP pose target (IK nearest the present joints)."""
        p = as_vector(pose6, 6, "servo target pose")
        with self._cond:
            self._require_motion_allowed()
            cached = self._servo_ik
            if cached is not None and np.array_equal(cached[0], p):
                q = cached[1]  # the program re-issues the same target every cycle
            else:
                q = self._ik_locked(p, self._q)
                self._servo_ik = (p, q)
            return self._servo("servol", q, time_s, lookahead_s, gain)

    def _servo(self, name: str, q: Vec, time_s: float, lookahead_s: float, gain: float) -> int:
        t = float(time_s)
        if not (math.isfinite(t) and t >= 0):
            raise CommandRejectedError(f"servo time must be >= 0, got {time_s!r}")
        if not 0.03 <= float(lookahead_s) <= 0.2:
            raise CommandRejectedError("servo lookahead must be in [0.03, 0.2] s")
        if not 100.0 <= float(gain) <= 2000.0:
            raise CommandRejectedError("servo gain must be in [100, 2000]")
        self._require_motion_allowed()
        self._check_joint_limits(q, "servo target")
        t = max(t, CYCLE_S)
        now, host_s = self._now(), time.monotonic()
        cmd = self._cmd
        # a braking servo of the same stream resumes (its stream history stays): after a host
        # stall the arm may have fallen behind the stream, which is no jump of the stream
        fresh = not (isinstance(cmd, Servo) and cmd.name == name)
        servo = Servo(self._new_id(), name, self._q, decel=10.0) if fresh else cmd
        assert isinstance(servo, Servo)
        v = servo.stream_velocity(q, t, host_s)
        if float(np.max(np.abs(v))) > self.limits.max_joint_speed_rad_s * _LIMIT_MARGIN:
            self._trip(f"{name} target needs more than the joint speed limit "
                       f"({float(np.max(np.abs(v))):.2f} rad/s)")
        servo.retarget(q, t, float(lookahead_s), float(gain), now, host_s)
        if fresh:
            self._install(servo)
        return servo.id

    # -- stops (always accepted) ---------------------------------------------------------------
    def speed_stop(self, decel: float = 10.0) -> None:
        """End speedj/speedl/jog with ``decel`` (rad/s^2 or m/s^2); other motion brakes too."""
        d = positive_number(decel, "deceleration")
        with self._cond:
            cmd = self._cmd
            now = self._now()
            if isinstance(cmd, SpeedJ):
                cmd.stop(d, now)
            elif isinstance(cmd, SpeedL):
                cmd.stop(d * 1000.0, now)
            elif cmd is not None:
                self._brake_now(d, "stop", CommandOutcome.PREEMPTED)

    def servo_stop(self, decel: float = 10.0) -> None:
        self.stop_j(decel)

    def stop_j(self, decel_rad_s2: float = 2.0) -> None:
        """Brake in joint space with ``decel``, ending any command."""
        d = positive_number(decel_rad_s2, "deceleration")
        with self._cond:
            if self._cmd is not None and self._cmd.name not in ("protective_stop",
                                                                "emergency_stop"):
                self._brake_now(d, "stopj", CommandOutcome.PREEMPTED)

    def stop_l(self, decel_m_s2: float = 10.0) -> None:
        """Brake so that the TCP decelerates at about ``decel``, ending any command."""
        d = positive_number(decel_m_s2, "deceleration")
        with self._cond:
            cmd = self._cmd
            if cmd is None or cmd.name in ("protective_stop", "emergency_stop"):
                return
            twist = self._kin.jacobian_tcp(self._q) @ self._qd
            v = max(float(np.linalg.norm(twist[:3])) / 1000.0, 1e-9)
            peak = float(np.max(np.abs(self._qd)))
            t_stop = v / d
            joint_decel = peak / t_stop if t_stop > 0 else d
            self._brake_now(max(joint_decel, 1e-6), "stopl", CommandOutcome.PREEMPTED)
