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

import math
import threading
import time
from collections import deque
from collections.abc import Sequence
from dataclasses import dataclass
from enum import Enum, IntEnum
from typing import Literal

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.spatial.transform import Rotation

from estimator.transforms import T_from_ur_pose, ur_pose_from_T
from fakes.ur_sim.kinematics import UnreachableError, UR5eKinematics
from fakes.ur_sim.profiles import BlendedLinearPath, JointProfile, LinearProfile

NUM_JOINTS = 6
CYCLE_S = 0.002  # 500 Hz, the e-Series control rate


class RobotMode(IntEnum):
    """UR RobotMode as RTDE ``robot_mode`` reports it."""

    NO_CONTROLLER = -1
    DISCONNECTED = 0
    CONFIRM_SAFETY = 1
    BOOTING = 2
    POWER_OFF = 3
    POWER_ON = 4
    IDLE = 5
    BACKDRIVE = 6
    RUNNING = 7


class SafetyMode(IntEnum):
    """UR SafetyMode as RTDE ``safety_mode`` reports it."""

    NORMAL = 1
    REDUCED = 2
    PROTECTIVE_STOP = 3
    RECOVERY = 4
    SAFEGUARD_STOP = 5
    SYSTEM_EMERGENCY_STOP = 6
    ROBOT_EMERGENCY_STOP = 7
    VIOLATION = 8
    FAULT = 9


class SafetyStatusBit(IntEnum):
    """Bit numbers of RTDE ``safety_status_bits``."""

    NORMAL_MODE = 0
    REDUCED_MODE = 1
    PROTECTIVE_STOPPED = 2
    RECOVERY_MODE = 3
    SAFEGUARD_STOPPED = 4
    SYSTEM_EMERGENCY_STOPPED = 5
    ROBOT_EMERGENCY_STOPPED = 6
    EMERGENCY_STOPPED = 7
    VIOLATION = 8
    FAULT = 9
    STOPPED_DUE_TO_SAFETY = 10


class RobotStatusBit(IntEnum):
    """Bit numbers of RTDE ``robot_status_bits``."""

    POWER_ON = 0
    PROGRAM_RUNNING = 1
    TEACH_BUTTON_PRESSED = 2
    POWER_BUTTON_PRESSED = 3


class EngineError(Exception):
    """Base class: the engine refused a command. Nothing moved because of it."""

    code = "sim_error"


class CommandRejectedError(EngineError):
    """The command itself is invalid: wrong shape, non-finite, outside joint limits,
    unreachable, or asking for more than the arm can do."""

    code = "command_rejected"


class UnreachablePoseError(CommandRejectedError):
    """No inverse-kinematics solution (or none inside the joint limits) for a target/path."""

    code = "unreachable"


class NotRunningError(EngineError):
    """Motion needs robot mode RUNNING (powered, brakes released)."""

    code = "not_running"


class ProtectiveStopActiveError(EngineError):
    """The arm is protective-stopped; motion is refused until :meth:`unlock_protective_stop`.

    Also raised by the command that itself trips the stop (e.g. a TCP speed over the limit).
    """

    code = "protective_stop"


class EmergencyStopActiveError(EngineError):
    """The arm is emergency-stopped; release the e-stop and power on again."""

    code = "emergency_stop"


@dataclass(frozen=True)
class SimLimits:
    """Safety configuration of the simulated arm (UR5e-like defaults)."""

    joint_min_rad: float = -6.283185307179586
    joint_max_rad: float = 6.283185307179586
    max_joint_speed_rad_s: float = 3.14159  # 180 deg/s, UR5e joint maximum
    max_joint_accel_rad_s2: float = 40.0
    max_tcp_speed_m_s: float = 1.5  # safety "tool speed" limit
    max_tcp_accel_m_s2: float = 15.0
    # Workspace the TCP must stay in (base frame, m): an axis-aligned box AND a sphere.
    workspace_min_m: tuple[float, float, float] = (-1.0, -1.0, -0.05)
    workspace_max_m: tuple[float, float, float] = (1.0, 1.0, 1.2)
    workspace_radius_m: float = 1.05
    protective_stop_decel_rad_s2: float = 20.0
    unlock_delay_s: float = 5.0  # a real controller refuses unlock for 5 s after the stop
    servo_watchdog_s: float = 0.02  # servo stream gap (beyond the command's time) before braking
    power_on_s: float = 0.3  # POWER_OFF -> POWER_ON -> IDLE
    brake_release_s: float = 0.4  # IDLE -> RUNNING


Pose6 = list[float]
JogFeature = Literal["base", "tool"]
PathKind = Literal["movej", "movel"]
# one waypoint of move_path: (kind, target, speed, accel, blend_m); target is q for "movej"
# and a pose6 for "movel"
PathEntry = tuple[PathKind, Sequence[float], float, float, float]
FaultKind = Literal["protective_stop", "emergency_stop"]


@dataclass(frozen=True)
class EngineSnapshot:
    """A consistent state of the arm, taken under the engine lock (RTDE output fields)."""

    timestamp_s: float  # controller uptime (RTDE ``timestamp``)
    host_monotonic_s: float  # time.monotonic() of the sample, for pose histories
    q: tuple[float, ...]  # actual_q (rad)
    qd: tuple[float, ...]  # actual_qd (rad/s)
    target_q: tuple[float, ...]
    target_qd: tuple[float, ...]
    target_qdd: tuple[float, ...]
    tcp_pose: tuple[float, ...]  # actual_TCP_pose, pose6
    tcp_speed: tuple[float, ...]  # actual_TCP_speed [vx, vy, vz (m/s), wx, wy, wz (rad/s)]
    target_tcp_pose: tuple[float, ...]
    target_tcp_speed: tuple[float, ...]
    tcp_offset: tuple[float, ...]  # pose6 of the TCP in the flange frame
    tcp_force: tuple[float, ...]  # always zero: no contact simulation
    joint_temperatures_c: tuple[float, ...]
    actual_current_a: tuple[float, ...]
    joint_modes: tuple[int, ...]  # UR JointMode per joint (253 RUNNING, 236 POWER_OFF, ...)
    robot_mode: RobotMode
    safety_mode: SafetyMode
    safety_status_bits: int
    robot_status_bits: int
    moving: bool
    active_command: str | None  # "movej", "movel", "path", "speedj", "speedl", "jog", ...
    async_progress: int  # -1 when no move runs, else index of the path segment under way
    speed_scaling: float  # actual speed scaling (0 while stopped by safety)
    target_speed_fraction: float  # the speed slider
    seconds_since_protective_stop: float | None  # None when not protective-stopped
    last_stop_reason: str  # why the last safety stop happened, "" if none
    last_command_id: int  # id returned by the latest accepted motion command (0: none yet)


class CommandOutcome(Enum):
    """What became of a motion command (see :meth:`MotionEngine.outcome`)."""

    RUNNING = "running"
    SUCCEEDED = "succeeded"  # arrived / stopped as asked
    ABORTED = "aborted"  # ended by a safety stop or power loss
    PREEMPTED = "preempted"  # replaced by a later command or a stop


Vec = NDArray[np.float64]
HOME_Q_RAD = (0.0, -1.571, 1.571, -1.571, -1.571, 0.0)  # tool pointing down, clear of the base
_JOINT_RUNNING, _JOINT_IDLE, _JOINT_POWER_OFF = 253, 255, 239
_LIMIT_MARGIN = 1.02  # profiles ride exactly at the limit; only real excess trips a stop
_PATH_SAMPLE_MM = 5.0  # movel paths are checked through IK at least this densely
_PATH_SAMPLE_RAD = 0.05
_MAX_PATH_JOINT_STEP_RAD = 0.35  # a bigger jump between samples means a configuration flip
_HISTORY_S = 10.0


class _SafetyTrip(Exception):
    """Raised inside a step when the motion itself cannot continue (e.g. IK lost)."""


@dataclass
class _Step:
    q: Vec
    qd: Vec
    qdd: Vec
    done: bool


class _Command:
    """One thing the arm is doing. ``step`` advances it to ``now`` from the engine state."""

    limited = True  # subject to the run-time safety checks (brakes are not)

    def __init__(self, cid: int, name: str) -> None:
        self.id = cid
        self.name = name
        self.progress = -1

    def step(self, eng: MotionEngine, now: float, dt: float) -> _Step:
        raise NotImplementedError


class _Brake(_Command):
    """Joint-proportional constant deceleration to rest: every joint stops at the same instant."""

    limited = False

    def __init__(self, cid: int, name: str, q0: Vec, qd0: Vec, decel: float) -> None:
        super().__init__(cid, name)
        self.q0, self.qd0 = q0.copy(), qd0.copy()
        peak = float(np.max(np.abs(qd0)))
        self.T = peak / decel if peak > 0 else 0.0
        self.t = 0.0

    @property
    def q_end(self) -> Vec:
        return self.q0 + 0.5 * self.T * self.qd0

    def step(self, eng: MotionEngine, now: float, dt: float) -> _Step:
        self.t += dt
        if self.t >= self.T:
            z = np.zeros(6)
            return _Step(self.q_end, z, z.copy(), True)
        t, T = self.t, self.T
        return _Step(self.q0 + self.qd0 * t - 0.5 * self.qd0 / T * t * t,
                     self.qd0 * (1.0 - t / T), -self.qd0 / T, False)


class _Then(_Command):
    """``first`` then ``second``: a profiled move commanded while the arm still moves brakes
    first, because a trapezoid starts from rest."""

    def __init__(self, first: _Brake, second: _Command) -> None:
        super().__init__(second.id, second.name)
        self.first, self.second = first, second
        self.limited = True

    def step(self, eng: MotionEngine, now: float, dt: float) -> _Step:
        if self.first is not None and self.first.t < self.first.T:
            out = self.first.step(eng, now, dt)
            out.done = False
            return out
        out = self.second.step(eng, now, dt)
        self.progress = self.second.progress
        return out


class _MoveJ(_Command):
    def __init__(self, cid: int, name: str, profile: JointProfile) -> None:
        super().__init__(cid, name)
        self.profile = profile
        self.tau = 0.0
        self.progress = 0

    def step(self, eng: MotionEngine, now: float, dt: float) -> _Step:
        f = eng._speed_fraction
        self.tau += dt * f
        q, qd, qdd = self.profile.at(self.tau)
        return _Step(q, qd * f, qdd * f * f, self.tau >= self.profile.duration_s)


class _MoveL(_Command):
    """Straight (or blended) TCP motion; joints follow by IK from the previous cycle."""

    def __init__(self, cid: int, name: str, path: BlendedLinearPath, first_entry: int = 0
                 ) -> None:
        super().__init__(cid, name)
        self.path = path
        self.tau = 0.0
        self.first_entry = first_entry
        self.progress = first_entry

    def step(self, eng: MotionEngine, now: float, dt: float) -> _Step:
        self.tau += dt * eng._speed_fraction
        done = self.tau >= self.path.duration_s
        self.progress = self.first_entry + self.path.index_at(self.tau)
        T = self.path.pose_at(self.tau)
        try:
            # the closed form lands the final pose exactly; Newton is plenty in between
            q = (eng._kin.inverse_tcp(T, eng._q) if done
                 else eng._kin.inverse_tcp_local(T, eng._q, eng._q + eng._qd * dt))
        except UnreachableError as err:
            raise _SafetyTrip("linear move lost its inverse kinematics") from err
        qd = (q - eng._q) / dt if dt > 0 else np.zeros(6)
        return _Step(q, qd, (qd - eng._qd) / dt if dt > 0 else np.zeros(6), done)


class _Path(_Command):
    def __init__(self, cid: int, segments: list[_Command]) -> None:
        super().__init__(cid, "path")
        self.segments = segments
        self.index = 0
        self.progress = 0

    def step(self, eng: MotionEngine, now: float, dt: float) -> _Step:
        seg = self.segments[self.index]
        out = seg.step(eng, now, dt)
        self.progress = seg.progress
        if out.done and self.index + 1 < len(self.segments):
            self.index += 1
            out.done = False
        return out


class _SpeedJ(_Command):
    """Ramp the joint velocity vector to a target; after ``expire_at`` the target is zero."""

    def __init__(self, cid: int, qd0: Vec, target: Vec, accel: float,
                 expire_at: float | None) -> None:
        super().__init__(cid, "speedj")
        self.qd = qd0.copy()
        self.target, self.accel, self.expire_at = target, accel, expire_at

    def stop(self, decel: float, now: float) -> None:
        self.accel, self.expire_at = decel, now

    def step(self, eng: MotionEngine, now: float, dt: float) -> _Step:
        stopping = self.expire_at is not None and now >= self.expire_at
        target = np.zeros(6) if stopping else self.target
        dv = target - self.qd
        m = float(np.max(np.abs(dv)))
        new = self.qd + dv * min(1.0, self.accel * dt / m) if m > 0 else self.qd.copy()
        q = eng._q + 0.5 * (self.qd + new) * dt
        qdd = (new - self.qd) / dt if dt > 0 else np.zeros(6)
        self.qd = new
        return _Step(q, new.copy(), qdd, stopping and not np.any(new))


class _SpeedL(_Command):
    """Cartesian velocity (base or tool frame) integrated on the TCP pose, joints by IK."""

    def __init__(self, cid: int, name: str, eng: MotionEngine, target: Vec, frame: JogFeature,
                 accel_mm_s2: float, accel_rad_s2: float, expire_at: float | None) -> None:
        super().__init__(cid, name)
        self.T = eng._kin.forward_tcp(eng._q)
        self.twist = eng._kin.jacobian_tcp(eng._q) @ eng._qd
        self.target, self.frame = target, frame
        self.acc_lin, self.acc_rot, self.expire_at = accel_mm_s2, accel_rad_s2, expire_at

    def stop(self, decel_mm_s2: float, now: float) -> None:
        self.acc_lin, self.acc_rot, self.expire_at = decel_mm_s2, decel_mm_s2 / 1000.0, now

    @staticmethod
    def _ramp(cur: Vec, target: Vec, accel: float, dt: float) -> Vec:
        dv = target - cur
        m = float(np.linalg.norm(dv))
        return cur + dv * min(1.0, accel * dt / m) if m > 0 else cur.copy()

    def step(self, eng: MotionEngine, now: float, dt: float) -> _Step:
        stopping = self.expire_at is not None and now >= self.expire_at
        target = np.zeros(6) if stopping else self.target.copy()
        if self.frame == "tool" and not stopping:
            R = self.T[:3, :3]
            target = np.concatenate([R @ target[:3], R @ target[3:]])
        new = np.concatenate([self._ramp(self.twist[:3], target[:3], self.acc_lin, dt),
                              self._ramp(self.twist[3:], target[3:], self.acc_rot, dt)])
        mean = 0.5 * (self.twist + new)
        T = self.T.copy()
        T[:3, 3] += mean[:3] * dt
        T[:3, :3] = (Rotation.from_rotvec(mean[3:] * dt) * Rotation.from_matrix(T[:3, :3])
                     ).as_matrix()
        try:
            q = eng._kin.inverse_tcp_local(T, eng._q, eng._q + eng._qd * dt)
        except UnreachableError as err:
            raise _SafetyTrip("Cartesian speed command left the reachable workspace") from err
        self.T, self.twist = T, new
        qd = (q - eng._q) / dt if dt > 0 else np.zeros(6)
        return _Step(q, qd, (qd - eng._qd) / dt if dt > 0 else np.zeros(6),
                     stopping and not np.any(new))


class _Servo(_Command):
    """Go to the latest target within its ``time_s``; brake when the stream dries up."""

    def __init__(self, cid: int, name: str, decel: float) -> None:
        super().__init__(cid, name)
        self.decel = decel
        self.q_from = np.zeros(6)
        self.q_to = np.zeros(6)
        self.t_cmd = 0.0
        self.time_s = CYCLE_S
        self.brake: _Brake | None = None

    def retarget(self, q_now: Vec, q_to: Vec, time_s: float, now: float) -> None:
        self.q_from, self.q_to, self.t_cmd, self.time_s = q_now.copy(), q_to, now, time_s
        self.brake = None

    @property
    def velocity(self) -> Vec:
        return (self.q_to - self.q_from) / self.time_s

    def step(self, eng: MotionEngine, now: float, dt: float) -> _Step:
        if self.brake is None and now > self.t_cmd + self.time_s + eng.limits.servo_watchdog_s:
            self.brake = _Brake(self.id, self.name, eng._q, eng._qd, self.decel)
        if self.brake is not None:
            return self.brake.step(eng, now, dt)
        elapsed = now - self.t_cmd
        if elapsed >= self.time_s:
            z = np.zeros(6)
            return _Step(self.q_to.copy(), z, (z - eng._qd) / dt if dt > 0 else z, False)
        v = self.velocity
        return _Step(self.q_from + v * elapsed, v, (v - eng._qd) / dt if dt > 0 else v * 0,
                     False)


def _vec(x: ArrayLike, n: int, what: str) -> Vec:
    try:
        v = np.asarray(x, dtype=float).reshape(-1)
    except (TypeError, ValueError) as err:
        raise CommandRejectedError(f"{what} must be {n} numbers") from err
    if v.shape != (n,) or not np.all(np.isfinite(v)):
        raise CommandRejectedError(f"{what} must be {n} finite numbers, got {x!r}")
    return v


def _positive(x: float, what: str, limit: float | None = None) -> float:
    v = float(x)
    if not (math.isfinite(v) and v > 0):
        raise CommandRejectedError(f"{what} must be a positive number, got {x!r}")
    if limit is not None and v > limit:
        raise CommandRejectedError(f"{what} {v:g} exceeds the arm's maximum {limit:g}")
    return v


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
        self._q = _vec(HOME_Q_RAD if q_rad is None else q_rad, NUM_JOINTS, "q_rad")
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
        self._cmd: _Command | None = None
        self._next_id = 1
        self._outcomes: dict[int, CommandOutcome] = {}
        self._timers: list[tuple[float, str]] = []  # (due monotonic, event)
        self._t0 = time.monotonic()
        self._last_step = self._t0
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

    def _run(self) -> None:
        next_t = time.monotonic()
        while True:
            with self._cond:
                if not self._alive:
                    return
                now = time.monotonic()
                self._run_timers(now)
                if not self._busy():
                    due = min((t for t, _ in self._timers), default=now + 1.0)
                    self._cond.wait(timeout=max(0.0, due - now))
                    next_t = time.monotonic()
                    continue
                dt = max(0.0, now - self._last_step)
                self._last_step = now
                self._step(now, dt)
            next_t += CYCLE_S
            delay = next_t - time.monotonic()
            if delay > 0:
                time.sleep(delay)
            elif delay < -0.05:
                next_t = time.monotonic()  # fell far behind (loaded machine): don't burst

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
                self._emergency_stop(now)
        self._cond.notify_all()

    def _step(self, now: float, dt: float) -> None:
        cmd = self._cmd
        assert cmd is not None
        try:
            out = cmd.step(self, now, dt)
        except _SafetyTrip as trip:
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
            return "TCP left the workspace"  # (moving back in from outside is allowed)
        return ""

    def _workspace_excess_m(self, T_base_tcp: Vec) -> float:
        """How far (m) the TCP is outside the workspace box or sphere (<= 0: inside)."""
        p = T_base_tcp[:3, 3] / 1000.0
        lo = np.asarray(self.limits.workspace_min_m)
        hi = np.asarray(self.limits.workspace_max_m)
        box = float(np.max(np.concatenate([lo - p, p - hi])))
        return max(box, float(np.linalg.norm(p)) - self.limits.workspace_radius_m)

    def _finish(self, outcome: CommandOutcome, then: _Command | None = None) -> None:
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

    def _emergency_stop(self, now: float) -> None:
        self._safety_mode = SafetyMode.ROBOT_EMERGENCY_STOP
        self._stop_reason = "emergency stop"
        self._timers = []
        self._brake_now(self.limits.protective_stop_decel_rad_s2, "emergency_stop",
                        CommandOutcome.ABORTED)
        if self._cmd is None:
            self._robot_mode = RobotMode.POWER_OFF

    def _brake_now(self, decel: float, name: str, outcome: CommandOutcome) -> None:
        """End the active command, braking from the present velocity."""
        brake = _Brake(0, name, self._q, self._qd, decel)
        self._finish(outcome, brake if brake.T > 0 else None)
        if self._cmd is None:
            self._qd = np.zeros(6)
            self._qdd = np.zeros(6)
        self._last_step = time.monotonic()
        self._cond.notify_all()

    # -- state ---------------------------------------------------------------------------
    def snapshot(self) -> EngineSnapshot:
        with self._cond:
            return self._snapshot_locked()

    def _snapshot_locked(self) -> EngineSnapshot:
        # While moving, the state belongs to the last control cycle, not to the reading instant.
        now = time.monotonic() if self._cmd is None else self._last_step
        q, qd = self._q, self._qd
        pose = tuple(ur_pose_from_T(self._kin.forward_tcp(q)))
        twist = self._kin.jacobian_tcp(q) @ qd
        twist[:3] /= 1000.0
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
            tcp_speed=tuple(map(float, twist)),
            target_tcp_pose=pose,
            target_tcp_speed=tuple(map(float, twist)),
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
                self._timers.append((time.monotonic() + self.limits.power_on_s, "idle"))
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
                           default=time.monotonic())
            self._timers.append((idle_due + self.limits.brake_release_s, "running"))
            self._cond.notify_all()

    def unlock_protective_stop(self) -> bool:
        """Clear a protective stop. False (refused) within ``unlock_delay_s`` of the stop."""
        with self._cond:
            if self._safety_mode != SafetyMode.PROTECTIVE_STOP:
                return self._safety_mode == SafetyMode.NORMAL
            assert self._stop_t is not None
            if time.monotonic() - self._stop_t < self.limits.unlock_delay_s:
                return False
            self._safety_mode = SafetyMode.NORMAL
            self._stop_t = None
            return True

    def trigger_protective_stop(self, reason: str = "triggered") -> None:
        """Brake quickly, abort the active command, refuse motion until unlocked."""
        with self._cond:
            if self._safety_mode not in _ESTOP:
                self._protective_stop(reason, time.monotonic())

    def trigger_emergency_stop(self) -> None:
        """Category-1 stop: brake, then power off; ROBOT_EMERGENCY_STOP until released."""
        with self._cond:
            self._emergency_stop(time.monotonic())

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
            self._timers.append((time.monotonic() + max(0.0, float(after_s)), fault))
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
        p = _vec(pose6, 6, "TCP pose")
        with self._cond:
            if self._cmd is not None:
                raise CommandRejectedError("cannot change the TCP while the arm moves")
            self._kin.set_tcp(T_from_ur_pose(p.tolist()))
            self._tcp_offset = [float(v) for v in p]

    def fk(self, q_rad: Sequence[float]) -> Pose6:
        """TCP pose6 of a joint vector, with the current TCP offset."""
        q = _vec(q_rad, 6, "q")
        with self._cond:
            return ur_pose_from_T(self._kin.forward_tcp(q))

    def ik(self, pose6: Sequence[float], q_near: Sequence[float] | None = None) -> list[float]:
        """Joints reaching the TCP pose6 nearest ``q_near`` (default: current q)."""
        p = _vec(pose6, 6, "pose")
        with self._cond:
            seed = self._q if q_near is None else _vec(q_near, 6, "q_near")
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
        self._protective_stop(reason, time.monotonic())
        raise ProtectiveStopActiveError(f"protective stop: {reason}")

    def _new_id(self) -> int:
        """The id the next installed command gets; consumed only by :meth:`_install`, so a
        rejected command leaves no trace."""
        return self._next_id

    def _rest_start(self, accel: float) -> tuple[Vec, _Brake | None]:
        """Where a profiled move will start: here, or where the present motion brakes to."""
        if self._cmd is None and not np.any(self._qd):
            return self._q.copy(), None
        brake = _Brake(0, "brake", self._q, self._qd, max(accel, 1.0))
        return brake.q_end, brake

    def _install(self, cmd: _Command, brake: _Brake | None = None) -> int:
        self._finish(CommandOutcome.PREEMPTED)
        self._next_id = cmd.id + 1
        self._outcomes[cmd.id] = CommandOutcome.RUNNING
        if len(self._outcomes) > 1000:
            for old in sorted(self._outcomes)[:500]:
                del self._outcomes[old]
        self._cmd = _Then(brake, cmd) if brake is not None and brake.T > 0 else cmd
        self._last_step = time.monotonic()
        self._cond.notify_all()
        return cmd.id

    def _plan_j(self, q0: Vec, q1: Vec, speed: float, accel: float, cid: int, name: str
                ) -> _MoveJ:
        self._check_joint_limits(q1, "target")
        return _MoveJ(cid, name, JointProfile(q0, q1, speed, accel))

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
        q1 = _vec(q_rad, 6, "target q")
        v = _positive(speed_rad_s, "joint speed", self.limits.max_joint_speed_rad_s)
        a = _positive(accel_rad_s2, "joint acceleration", self.limits.max_joint_accel_rad_s2)
        with self._cond:
            self._require_motion_allowed()
            q0, brake = self._rest_start(a)
            cmd = self._plan_j(q0, q1, v, a, self._new_id(), "movej")
            return self._install(cmd, brake)

    def move_j_ik(self, pose6: Sequence[float], speed_rad_s: float, accel_rad_s2: float) -> int:
        """Joint move to the IK solution of a TCP pose nearest the current q (URScript movej(p))."""
        p = _vec(pose6, 6, "target pose")
        v = _positive(speed_rad_s, "joint speed", self.limits.max_joint_speed_rad_s)
        a = _positive(accel_rad_s2, "joint acceleration", self.limits.max_joint_accel_rad_s2)
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
        p = _vec(pose6, 6, "target pose")
        v = _positive(speed_m_s, "tool speed")
        a = _positive(accel_m_s2, "tool acceleration", self.limits.max_tcp_accel_m_s2)
        with self._cond:
            self._require_motion_allowed()
            q0, brake = self._rest_start(a)
            prof, _ = self._plan_l(q0, p, v, a)
            return self._install(_MoveL(self._new_id(), "movel", BlendedLinearPath([prof], [])),
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
            segments: list[_Command] = []
            run: list[LinearProfile] = []  # movel profiles to be blended together
            run_blends: list[float] = []
            run_first = 0
            for i, entry in enumerate(path):
                kind, tgt, v, a, blend = self._path_entry(i, entry)
                if kind == "movej":
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
                run_blends.append(blend * 1000.0 if nxt == "movel" else 0.0)
            if run:
                segments.append(self._blended(cid, run, run_blends[:-1], run_first))
            return self._install(_Path(cid, segments), brake)

    @staticmethod
    def _blended(cid: int, run: list[LinearProfile], blends_mm: list[float], first: int
                 ) -> _MoveL:
        return _MoveL(cid, "movel", BlendedLinearPath(run, blends_mm), first)

    def _path_entry(self, i: int, entry: PathEntry) -> tuple[PathKind, Vec, float, float, float]:
        try:
            kind, target, speed, accel, blend = entry
        except (TypeError, ValueError) as err:
            raise CommandRejectedError(
                f"path entry {i} must be (kind, target, speed, accel, blend)") from err
        b = float(blend)
        if not (math.isfinite(b) and b >= 0):
            raise CommandRejectedError(f"path entry {i}: blend must be >= 0")
        tgt = _vec(target, 6, f"path entry {i} target")
        if kind == "movej":
            v = _positive(speed, f"path entry {i} speed", self.limits.max_joint_speed_rad_s)
            a = _positive(accel, f"path entry {i} accel", self.limits.max_joint_accel_rad_s2)
        elif kind == "movel":
            v = _positive(speed, f"path entry {i} speed")
            a = _positive(accel, f"path entry {i} accel", self.limits.max_tcp_accel_m_s2)
        else:
            raise CommandRejectedError(f"path entry {i}: unknown kind {kind!r}")
        return kind, tgt, v, a, b

    # -- streamed motion ---------------------------------------------------------------------
    def _expiry(self, time_s: float) -> float | None:
        t = float(time_s)
        if not math.isfinite(t):
            raise CommandRejectedError(f"time must be finite, got {time_s!r}")
        return time.monotonic() + t if t > 0 else None

    def speed_j(self, qd_rad_s: Sequence[float], accel_rad_s2: float, time_s: float = 0.0
                ) -> int:
        """Joint velocity. Brakes with ``accel`` when no new command arrives within ``time_s``
        (``time_s <= 0``: runs until :meth:`speed_stop` or another command)."""
        qd = _vec(qd_rad_s, 6, "joint speeds")
        a = _positive(accel_rad_s2, "joint acceleration", self.limits.max_joint_accel_rad_s2)
        expire = self._expiry(time_s)
        with self._cond:
            self._require_motion_allowed()
            if float(np.max(np.abs(qd))) > self.limits.max_joint_speed_rad_s:
                self._trip("speedj above the joint speed limit")
            cmd = _SpeedJ(self._new_id(), self._qd, qd, a, expire)
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
        twist = _vec(xd, 6, "TCP speeds")
        a = _positive(accel_m_s2, "tool acceleration", self.limits.max_tcp_accel_m_s2)
        expire = self._expiry(time_s)
        with self._cond:
            self._require_motion_allowed()
            if float(np.linalg.norm(twist[:3])) > self.limits.max_tcp_speed_m_s:
                self._trip(f"{name} above the tool speed limit")
            target = np.concatenate([twist[:3] * 1000.0, twist[3:]])
            cmd = _SpeedL(self._new_id(), name, self, target, frame, a * 1000.0, a, expire)
            return self._install(cmd)

    def jog_stop(self, decel_m_s2: float = 0.5) -> None:
        self.speed_stop(decel_m_s2 if decel_m_s2 > 0 else 0.5)

    def servo_j(
        self, q_rad: Sequence[float], time_s: float = CYCLE_S, lookahead_s: float = 0.1,
        gain: float = 300.0,
    ) -> int:
        """Go to ``q`` within ``time_s``; the stream must keep coming (watchdog) or the arm
        brakes. ``lookahead_s``/``gain`` are range-checked like URScript's, not modelled."""
        q = _vec(q_rad, 6, "servo target q")
        with self._cond:
            return self._servo("servoj", q, time_s, lookahead_s, gain)

    def servo_l(
        self, pose6: Sequence[float], time_s: float = CYCLE_S, lookahead_s: float = 0.1,
        gain: float = 300.0,
    ) -> int:
        """As :meth:`servo_j` with a TCP pose target (IK nearest the present joints)."""
        p = _vec(pose6, 6, "servo target pose")
        with self._cond:
            self._require_motion_allowed()
            return self._servo("servol", self._ik_locked(p, self._q), time_s, lookahead_s, gain)

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
        now = time.monotonic()
        cmd = self._cmd
        if not (isinstance(cmd, _Servo) and cmd.name == name and cmd.brake is None):
            cmd = _Servo(self._new_id(), name, decel=10.0)
            cmd.retarget(self._q, q, t, now)
            self._install(cmd)
        else:
            cmd.retarget(self._q, q, t, now)
        if float(np.max(np.abs(cmd.velocity))) > self.limits.max_joint_speed_rad_s * _LIMIT_MARGIN:
            self._trip(f"{name} target needs more than the joint speed limit")
        return cmd.id

    # -- stops (always accepted) ---------------------------------------------------------------
    def speed_stop(self, decel: float = 10.0) -> None:
        """End speedj/speedl/jog with ``decel`` (rad/s^2 or m/s^2); other motion brakes too."""
        d = _positive(decel, "deceleration")
        with self._cond:
            cmd = self._cmd
            now = time.monotonic()
            if isinstance(cmd, _SpeedJ):
                cmd.stop(d, now)
            elif isinstance(cmd, _SpeedL):
                cmd.stop(d * 1000.0, now)
            elif cmd is not None:
                self._brake_now(d, "stop", CommandOutcome.PREEMPTED)

    def servo_stop(self, decel: float = 10.0) -> None:
        self.stop_j(decel)

    def stop_j(self, decel_rad_s2: float = 2.0) -> None:
        """Brake in joint space with ``decel``, ending any command."""
        d = _positive(decel_rad_s2, "deceleration")
        with self._cond:
            if self._cmd is not None and self._cmd.name not in ("protective_stop",
                                                                "emergency_stop"):
                self._brake_now(d, "stopj", CommandOutcome.PREEMPTED)

    def stop_l(self, decel_m_s2: float = 10.0) -> None:
        """Brake so that the TCP decelerates at about ``decel``, ending any command."""
        d = _positive(decel_m_s2, "deceleration")
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
