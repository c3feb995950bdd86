"""THE one path to the arm: the motion slot and the guarded arm.

Every command that can move the arm goes through :class:`GuardedArm`, which implements the
whole :class:`drivers.arm.Arm` protocol over the real (or simulated) arm and checks each
motion command against the configured limits before anything is sent. A refusal raises the
limit's :class:`cell.errors.CellError` and nothing moves. ``tests/cell/motion/test_motion_path.py``
fails when any module other than this one calls an arm's motion methods.

Rules it keeps, whoever calls it (approach, jog, teach, calibration routine, home, CLI):
- a motion command needs the :class:`MotionSlot` held (one motion at a time) and is refused
  once the holder has been cancelled, so a stop really stops. The last check of that flag and
  the command that starts the motion happen under one lock that the stop takes too
  (:class:`CommandGate`): a command either reaches the controller before the stop, which then
  ends it, or sees the flag and is never sent. Checking the flag only before the path check
  left a window (a joint move's path check asks the controller for its kinematics) in which a
  stop could reach the controller first and the move then ran to its end;
- the arm must be connected, powered, free of safety stops, and its state fresh;
- speed and acceleration within the caps (and above the floor: a speed that rounds to
  nothing on the wire would creep for hours);
- the whole interpolated path within the box and the tilt limit (see ``SafetyGuard``);
- a blocking move is sent without waiting (under the gate) and then watched to its end: it
  returns only when the controller says it is over and the arm is at the goal; any other end
  (cancelled, fault, short) leaves the arm commanded to stop and still before the error reaches
  the caller, so the slot is never released over a moving arm.
"""

from __future__ import annotations

import logging
import threading
import time
from collections import deque
from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager
from dataclasses import dataclass, field
from typing import Literal

import numpy as np
from numpy.typing import NDArray
from scipy.spatial.transform import Rotation

from cell.config.schema import LimitsConfig
from cell.error_codes import ErrorCode
from cell.errors import Cancelled, CellError, LimitError, RefusedError, UnavailableError
from cell.motion.limits import SafetyGuard, linear_path
from cell.motion.reach import ArmAt, PhaseReach, Posture, ReachReport
from cell.motion.twist import extrapolate_tcp
from drivers.arm import Arm, ArmState, JogFrame
from drivers.errors import (
    ConnectionLostError,
    DeviceTimeoutError,
    DriverError,
    EmergencyStopError,
    ProtectiveStopError,
)
from estimator.transforms import make_T, pose_distance

log = logging.getLogger(__name__)
Matrix4 = NDArray[np.float64]

AT_GOAL_MM = 0.2  # a move that ends further than this from its goal has failed
AT_GOAL_DEG = 0.1
JOINT_PATH_STEP_DEG = 3.0  # sampling of a joint move for the envelope and tilt checks
JOG_HORIZON_S = 0.15  # a continuous jog is checked this far ahead
SERVO_ACCEL_MARGIN = 1.5  # tick timing jitter: the law's own dt and the guard's differ
SERVO_MIN_DT_S = 0.008  # ticks closer than this are judged as this far apart (min tick)
SETTLE_TIMEOUT_S = 10.0


def driver_error(err: DriverError, what: str, device: str = "arm") -> CellError:
    """A hardware error as the cell reports it: unavailable when the device cannot be
    reached (the arm's lost link is ``arm_disconnected``), otherwise refused in the current
    state with the driver's code."""
    text = f"{what}: {err}"
    if isinstance(err, ProtectiveStopError | EmergencyStopError):
        text = (f"the arm stopped on a safety stop while {what}: {err}; clear the cause, "
                "then unlock")
    if isinstance(err, ConnectionLostError):
        code = ErrorCode.arm_disconnected if device == "arm" else ErrorCode(err.code)
        return UnavailableError(code, text)
    if isinstance(err, DeviceTimeoutError):
        return UnavailableError(ErrorCode(err.code), text)
    return RefusedError(ErrorCode(err.code), text)


@dataclass
class Motion:
    """The one motion slot's holder: who, and how to cancel it (with the reason, when a
    fault rather than a person cancelled it)."""

    name: str
    cancel: threading.Event = field(default_factory=threading.Event)
    job_id: str | None = None
    needs_camera: bool = False
    reason: CellError | None = None

    def cancel_with(self, reason: CellError | None = None) -> None:
        if reason is not None and self.reason is None:
            self.reason = reason
        self.cancel.set()

    def raise_if_cancelled(self, what: str) -> None:
        if self.cancel.is_set():
            if self.reason is not None:
                raise type(self.reason)(self.reason.code, self.reason.message)
            raise Cancelled(ErrorCode.cancelled, f"stopped by request {what}")


class MotionSlot:
    """One motion at a time: approach, jog, teach, calibration and home each hold it."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._motion: Motion | None = None
        self._generation = 0  # counts claims and releases: readers of cached state compare it

    @property
    def generation(self) -> int:
        return self._generation

    @property
    def current(self) -> Motion | None:
        with self._lock:
            return self._motion

    def claim(self, name: str, *, needs_camera: bool = False) -> Motion:
        """Take the slot (RefusedError ``busy`` when it is taken)."""
        with self._lock:
            if self._motion is not None:
                raise RefusedError(ErrorCode.busy,
                                   f"the arm is busy ({self._motion.name}); wait for it "
                                   "to finish or stop it")
            self._motion = Motion(name, needs_camera=needs_camera)
            self._generation += 1
            return self._motion

    def release(self, motion: Motion) -> None:
        with self._lock:
            if self._motion is motion:
                self._motion = None
                self._generation += 1

    @contextmanager
    def hold(self, name: str, *, needs_camera: bool = False) -> Iterator[Motion]:
        motion = self.claim(name, needs_camera=needs_camera)
        try:
            yield motion
        finally:
            self.release(motion)

    def release_unless_cancelled(self, motion: Motion) -> bool:
        """Release ``motion``'s hold as one step with the check that it was not cancelled:
        False (still held) when it was. A job that ends this way cannot be cancelled after it
        has reported success, and a stop that cancelled it in time always sees it end
        cancelled."""
        with self._lock:
            if motion.cancel.is_set():
                return False
            if self._motion is motion:
                self._motion = None
                self._generation += 1
            return True

    def cancel(self, reason: CellError | None = None) -> Motion | None:
        """Cancel whatever holds the slot; returns it (None when idle)."""
        with self._lock:
            motion = self._motion
            if motion is not None:
                motion.cancel_with(reason)
            return motion


class CommandGate:
    """Orders motion commands against stops.

    A stop first sets the holder's cancel flag, then sends the stop holding this lock. A
    command checks the flag and is sent holding it too. So either the command went out first
    (and the stop, sent after it, ends it) or the flag was already set (and it is never sent).
    Without the lock the stop could overtake a command that had passed its check, and the
    command would start after the stop had answered. Every device the cell moves (the arm, the
    gripper) sends its commands through the one gate.
    """

    def __init__(self) -> None:
        self._lock = threading.Lock()

    @contextmanager
    def command(self, motion: Motion, what: str) -> Iterator[None]:
        """Hold the gate for one command: Cancelled (nothing sent) once ``motion`` is."""
        with self._lock:
            motion.raise_if_cancelled(f"before the {what}")
            yield

    @contextmanager
    def stopping(self) -> Iterator[None]:
        """Hold the gate while a stop is sent: no command can start meanwhile."""
        with self._lock:
            yield


CommandKind = Literal["move_linear", "move_joint", "jog", "servo", "stop"]


@dataclass(frozen=True)
class Commanded:
    """A command that passed the guard and was sent to the arm (for audits and tests)."""

    t_s: float  # time.monotonic()
    kind: CommandKind
    T_base_tcp: Matrix4 | None  # goal of a move (for a joint move: its FK), None for stop
    velocity: NDArray[np.float64] | None = None  # jog twist [mm/s, rad/s]
    frame: JogFrame = "base"
    T_from: Matrix4 | None = None  # where the arm was when checked (servo: the reading moved on)
    path: tuple[Matrix4, ...] = ()  # the sampled path it was checked on


class GuardedArm:
    """:class:`drivers.arm.Arm` with every motion command checked first (see module doc)."""

    def __init__(self, arm: Arm, limits: LimitsConfig, slot: MotionSlot | None = None,
                 history: int = 2000, gate: CommandGate | None = None,
                 model: str = "ur5e") -> None:
        self._arm = arm
        self.guard = SafetyGuard(limits, model)
        self.slot = slot if slot is not None else MotionSlot()
        self.gate = gate if gate is not None else CommandGate()
        self._commanded: deque[Commanded] = deque(maxlen=history)
        self._lock = threading.Lock()
        self._last_twist: tuple[float, NDArray[np.float64]] | None = None  # (t, twist)

    @property
    def limits(self) -> LimitsConfig:
        return self.guard.limits

    @property
    def raw(self) -> Arm:
        """The unguarded arm, for the link supervisor (connect, reconnect) only."""
        return self._arm

    def commanded(self) -> list[Commanded]:
        with self._lock:
            return list(self._commanded)

    def _record(self, c: Commanded) -> None:
        with self._lock:
            self._commanded.append(c)

    # -- pass-through: connection, power, state ---------------------------------------------
    def connect(self) -> None:
        self._arm.connect()

    def disconnect(self) -> None:
        self._arm.disconnect()

    def power_on(self) -> None:
        self._arm.power_on()

    def power_off(self) -> None:
        self._arm.power_off()

    def set_tcp(self, T_flange_tcp: Matrix4) -> None:
        self._arm.set_tcp(T_flange_tcp)

    def state(self) -> ArmState:
        return self._arm.state()

    def tcp_pose(self) -> Matrix4:
        return self._arm.tcp_pose()

    def joint_positions_rad(self) -> NDArray[np.float64]:
        return self._arm.joint_positions_rad()

    def forward_kinematics(self, joints_rad: NDArray[np.float64]) -> Matrix4:
        return self._arm.forward_kinematics(joints_rad)

    def pose_at(self, timestamp_s: float) -> Matrix4:
        return self._arm.pose_at(timestamp_s)

    def is_moving(self) -> bool:
        return self._arm.is_moving()

    def wait_for_motion(self, timeout_s: float | None = None) -> None:
        """Watch the last move to its end (it starts nothing)."""
        self._arm.wait_for_motion(timeout_s)

    def recover_protective_stop(self) -> None:
        self._arm.recover_protective_stop()

    @property
    def last_twist_s(self) -> float | None:
        """When the last servo tick was accepted (``time.monotonic()``; None: none since the
        last stop). A loop that takes its acceleration step over the time since then agrees
        with the check, which judges the change over the time since then too."""
        last = self._last_twist
        return None if last is None else last[0]

    def stop(self, decel_mm_s2: float = 2000.0) -> None:
        """Always passed on: stopping is never refused. Sent holding the gate, so it follows
        any command already on its way and no command passes until it is sent."""
        with self.gate.stopping():
            self._last_twist = None
            self._record(Commanded(time.monotonic(), "stop", None))
            self._arm.stop(decel_mm_s2)

    # -- checks ------------------------------------------------------------------------------
    def ready_state(self) -> ArmState:
        """The arm's state, checked: connected, ready, fresh (CellError otherwise)."""
        try:
            st = self._arm.state()
        except DriverError as err:
            raise driver_error(err, "reading the arm state") from err
        self.guard.check_arm(st, time.monotonic())
        return st

    def _holder(self, what: str) -> Motion:
        motion = self.slot.current
        if motion is None:
            raise RefusedError(ErrorCode.no_motion_slot,
                               f"{what} refused: motion commands need the "
                               "cell's motion slot (internal error: report it)")
        motion.raise_if_cancelled(f"before the {what}")
        return motion

    # -- motion ------------------------------------------------------------------------------
    def move_linear(self, T_base_tcp: Matrix4, speed_mm_s: float, accel_mm_s2: float,
                    wait: bool = True, what: str = "move") -> None:
        """Checked straight move; with ``wait`` (the cell's way) returns at the goal."""
        motion = self._holder(what)
        self.guard.check_speed(float(speed_mm_s), float(accel_mm_s2))
        st = self.ready_state()
        T_goal = np.asarray(T_base_tcp, dtype=float)
        self.guard.check_goal(st.T_base_tcp, T_goal, what, st)
        self._record(Commanded(time.monotonic(), "move_linear", T_goal.copy(),
                               T_from=st.T_base_tcp.copy()))
        self._run(motion, what, T_goal, lambda: self._arm.move_linear(
            T_goal, speed_mm_s, accel_mm_s2, wait=False), wait)

    def move_joint(self, joints_rad: NDArray[np.float64], speed_rad_s: float,
                   accel_rad_s2: float, wait: bool = True, what: str = "joint move") -> None:
        """Checked joint move: the path (linear in joint space, as the controller moves) is
        sampled through the controller's own kinematics against the box and tilt limit."""
        motion = self._holder(what)
        self.guard.check_joint_speed(float(speed_rad_s), float(accel_rad_s2))
        q1 = np.asarray(joints_rad, dtype=float).reshape(-1)
        st, path = self.check_joint_move(q1, what)
        T_goal = path[-1]
        self._record(Commanded(time.monotonic(), "move_joint", T_goal.copy(),
                               T_from=st.T_base_tcp.copy(), path=tuple(path)))
        self._run(motion, what, T_goal, lambda: self._arm.move_joint(
            q1, speed_rad_s, accel_rad_s2, wait=False), wait)

    def check_joint_move(self, joints_rad: NDArray[np.float64], what: str = "joint move"
                         ) -> tuple[ArmState, list[Matrix4]]:
        """The arm's state and the sampled TCP path of a joint move from where it is now, after
        checking it (CellError when refused); callers use it to refuse before a job starts."""
        q1 = np.asarray(joints_rad, dtype=float).reshape(-1)
        if q1.shape != (6,) or not np.all(np.isfinite(q1)):
            raise RefusedError(ErrorCode.invalid_pose, f"the {what} needs 6 finite joint values")
        st = self.ready_state()
        self.guard.reach.check_joints(q1, what, st)
        q0 = np.asarray(st.joints_rad, dtype=float)
        n = max(2, int(np.ceil(np.degrees(np.max(np.abs(q1 - q0))) / JOINT_PATH_STEP_DEG)) + 1)
        try:
            path = [st.T_base_tcp] + [self._arm.forward_kinematics(q0 + u * (q1 - q0))
                                      for u in np.linspace(0.0, 1.0, n)[1:]]
        except DriverError as err:
            raise driver_error(err, f"checking the {what}") from err
        self.guard.check_path(path, what)
        return st, path

    def check_reachable(self, poses: Sequence[tuple[str, Matrix4]],
                        moves: Literal["linear", "joint"] = "linear") -> ReachReport:
        """A sequence of TCP poses, each with its phase's name ("pre-pick", "grasp",
        "retract", "place"), checked before anything moves: each reached from the one before
        (the first from where the arm is) by a straight move (``linear``: in the arm's
        configuration, along the sampled path) or a joint move (``joint``: the solution
        nearest the joints before), against the box, the tilt limit and the reach. Reports
        the joints at each pose, up to the first that fails and why; it moves nothing."""
        at: ArmAt = self.ready_state()
        out: list[PhaseReach] = []
        for phase, T in poses:
            T_goal = np.asarray(T, dtype=float)
            what = f"move to the {phase} pose"
            try:
                if T_goal.shape != (4, 4) or not np.all(np.isfinite(T_goal)):
                    raise LimitError(ErrorCode.invalid_pose, f"the {phase} pose is not finite")
                if moves == "linear":
                    self.guard.check_goal(at.T_base_tcp, T_goal, what)
                    q = self.guard.reach.check_path(linear_path(at.T_base_tcp, T_goal), what,
                                                    at)[-1]
                else:
                    q = self.guard.reach.joints_for(T_goal, what, at)
                    self.guard.check_path(self.guard.reach.joint_path(
                        at.joints_rad, q, at, JOINT_PATH_STEP_DEG), what)
            except LimitError as err:
                out.append(PhaseReach(phase, T_goal, None, err))
                break
            out.append(PhaseReach(phase, T_goal, q))
            at = Posture(q, T_goal)
        return ReachReport(tuple(out))

    def jog(self, velocity: NDArray[np.float64], frame: JogFrame = "base",
            accel_mm_s2: float = 500.0) -> None:
        """Checked velocity command: caps, and the path ``JOG_HORIZON_S`` ahead."""
        motion = self._holder("jog")
        v = np.asarray(velocity, dtype=float).reshape(-1)
        if v.shape != (6,):
            raise RefusedError(ErrorCode.invalid_request, "a jog needs [vx, vy, vz, wx, wy, wz]")
        self.guard.check_jog_speed(v[:3], np.degrees(v[3:]))
        if not 0 < accel_mm_s2 <= self.limits.max_accel_mm_s2:
            raise RefusedError(ErrorCode.accel_limit,
                               f"jog acceleration {accel_mm_s2} mm/s^2 is outside "
                               f"(0, {self.limits.max_accel_mm_s2}]")
        st = self.ready_state()
        self.guard.check_jog_ahead(st.T_base_tcp, jog_ahead(st.T_base_tcp, v, frame,
                                                            JOG_HORIZON_S), st)
        self._record(Commanded(time.monotonic(), "jog", None, v.copy(), frame,
                               T_from=st.T_base_tcp.copy()))
        try:
            with self.gate.command(motion, "jog"):
                self._arm.jog(v, frame, accel_mm_s2)
        except DriverError as err:
            self.settle()
            raise driver_error(err, "jogging") from err

    def servo_twist(self, velocity: NDArray[np.float64], accel_mm_s2: float,
                    watchdog_s: float, angular_accel_rad_s2: float | None = None) -> None:
        """One checked tick of a streamed base-frame twist (closed-loop control).

        Checked every tick: the slot's holder is not cancelled; the arm is ready and fresh;
        linear and angular speed under the caps; both accelerations under their caps
        (``angular_accel_rad_s2`` None: ``accel_mm_s2 / 1000`` rad/s^2, UR's rule); the
        change from the previous tick within them, translation and rotation each against its
        own; and where the twist leads if it ran on until the watchdog fires and the arm then
        braked (``watchdog_s + |v| / 2a``, per part) stays in the box and the tilt limit.
        Recorded with that pose ahead.
        """
        v = np.asarray(velocity, dtype=float).reshape(-1)
        if v.shape != (6,) or not np.all(np.isfinite(v)):
            raise RefusedError(ErrorCode.invalid_request, "a servo twist needs 6 finite values")
        lim = self.limits
        if not 0 < accel_mm_s2 <= lim.max_accel_mm_s2:
            raise LimitError(ErrorCode.accel_limit, f"servo acceleration {accel_mm_s2} mm/s^2 is "
                             f"outside (0, {lim.max_accel_mm_s2}]")
        alpha = accel_mm_s2 / 1000.0 if angular_accel_rad_s2 is None \
            else float(angular_accel_rad_s2)
        if not (np.isfinite(alpha) and 0 < np.degrees(alpha)
                <= lim.max_angular_accel_deg_s2 * (1 + 1e-9)):
            raise LimitError(ErrorCode.accel_limit, f"servo angular acceleration "
                             f"{np.degrees(alpha):.0f} deg/s^2 is outside (0, "
                             f"{lim.max_angular_accel_deg_s2}]")
        lin, ang_deg = float(np.linalg.norm(v[:3])), float(np.degrees(np.linalg.norm(v[3:])))
        if lin > lim.max_speed_mm_s * (1 + 1e-9):
            raise LimitError(ErrorCode.speed_limit, f"servo speed {lin:.1f} mm/s is above "
                             f"limits.max_speed_mm_s = {lim.max_speed_mm_s}")
        if ang_deg > lim.max_angular_speed_deg_s * (1 + 1e-9):
            raise LimitError(ErrorCode.speed_limit, f"servo rotation {ang_deg:.1f} deg/s is above "
                             f"limits.max_angular_speed_deg_s = {lim.max_angular_speed_deg_s}")
        with self.gate.command(self._holder("servo tick"), "servo tick"):
            now = time.monotonic()
            prev = self._last_twist
            # the change is judged against the last tick or against rest, whichever is
            # closer: a twist near rest is always safe to send (after a pause the arm's
            # watchdog may have braked it, and the controller may have restarted from zero)
            refs = [np.zeros(6)] if prev is None else [prev[1], np.zeros(6)]
            dt = SERVO_MIN_DT_S if prev is None else max(SERVO_MIN_DT_S, now - prev[0])
            dv, dw = min((twist_change(v, r, dt) for r in refs),
                         key=lambda c: max(c[0] / accel_mm_s2, c[1] / alpha))
            if not servo_change_ok(dv, dw, accel_mm_s2, alpha):
                raise LimitError(ErrorCode.accel_limit, f"servo twist changes at {dv:.0f} mm/s^2 / "
                                 f"{np.degrees(dw):.0f} deg/s^2, above {accel_mm_s2} mm/s^2 "
                                 f"/ {np.degrees(alpha):.0f} deg/s^2")
            st = self.ready_state()
            T_read = T_now = st.T_base_tcp
            if prev is not None:
                # the reading is a few ms old (more on a loaded host): since it was taken the
                # arm has gone on at the last twist, until that twist's watchdog ran out
                moved_s = min(time.monotonic(), prev[0] + watchdog_s) - st.timestamp_s
                T_now = extrapolate_tcp(T_read, prev[1], min(max(moved_s, 0.0), watchdog_s))
            T_ahead = servo_ahead(T_now, v, accel_mm_s2, watchdog_s, alpha)
            path = linear_path(T_now, T_ahead)
            self.guard.check_path(path, "servo motion", st)
            if T_now is not T_read:
                # and from the reading itself, never less careful than without the move-on
                # (its end points only: the box is convex, the turn within a tick tiny; the
                # sampled path costs 0.4 ms of a tick the frame thread needs the GIL for)
                self.guard.check_path([T_read, servo_ahead(
                    T_read, v, accel_mm_s2, watchdog_s, alpha)], "servo motion")
            self._record(Commanded(now, "servo", T_ahead, v.copy(), "base",
                                   T_from=T_now.copy(), path=(path[0], path[-1])))
            try:
                self._arm.servo_twist(v, accel_mm_s2, watchdog_s, alpha)
            except DriverError as err:
                self._last_twist = None
                self._arm.stop()
                raise driver_error(err, "servoing") from err
            self._last_twist = (now, v.copy())

    def _run(self, motion: Motion, what: str, T_goal: Matrix4, send: Callable[[], None],
             wait: bool) -> None:
        """Send a checked move through the gate without waiting; with ``wait`` watch it to its
        end and verify how it ended (see module doc)."""
        try:
            with self.gate.command(motion, what):
                send()
            if wait:
                self._arm.wait_for_motion()
        except DriverError as err:
            self.settle()
            motion.raise_if_cancelled(f"while moving to the {what}")
            raise driver_error(err, f"moving to the {what}") from err
        except BaseException:
            self.settle()
            raise
        if not wait:
            return
        try:
            reached = self._arm.state().T_base_tcp
        except DriverError as err:
            raise driver_error(err, f"reading the arm after the {what}") from err
        d_mm, d_deg = pose_distance(reached, T_goal)
        if d_mm <= AT_GOAL_MM and d_deg <= AT_GOAL_DEG:
            return
        self.settle()
        motion.raise_if_cancelled(f"while moving to the {what}")
        raise RefusedError(ErrorCode.motion_failed,
                           f"the arm stopped {d_mm:.2f} mm / {d_deg:.2f} deg "
                           f"short of the {what}")

    def settle(self, timeout_s: float = SETTLE_TIMEOUT_S, decel_mm_s2: float = 2000.0,
               poll_s: float = 0.01) -> Settled:
        """Command a stop and wait until the arm stands still, reading it every ``poll_s`` for
        ``timeout_s`` at most. Never raises, since it is how every failed motion and every
        closed loop ends: a stop the driver refuses is logged and reported in the answer."""
        t0 = time.monotonic()
        refused: DriverError | None = None
        try:
            self.stop(decel_mm_s2)
        except DriverError as err:
            log.warning("a stop was not accepted: %s", err)
            refused = err
        while time.monotonic() < t0 + timeout_s:
            try:
                if not self._arm.state().moving:
                    return Settled(True, time.monotonic() - t0, refused)
            except DriverError:
                return Settled(False, time.monotonic() - t0, refused)
            time.sleep(poll_s)
        log.error("the arm still moves %.0f s after a stop was commanded", timeout_s)
        return Settled(False, time.monotonic() - t0, refused)


@dataclass(frozen=True)
class Settled:
    """How a stop ended: ``still``, the arm stood within the timeout (False too when it could
    not be read); ``took_s``, since the stop was commanded; ``refused``, the driver's error
    when the stop command itself was not accepted."""

    still: bool
    took_s: float
    refused: DriverError | None = None


def jog_ahead(T: Matrix4, velocity: NDArray[np.float64], frame: JogFrame,
              horizon_s: float) -> Matrix4:
    """Where a jog at ``velocity`` (mm/s, rad/s) leads from ``T`` within ``horizon_s``."""
    v, w = velocity[:3], velocity[3:]
    dR = Rotation.from_rotvec(w * horizon_s).as_matrix()
    if frame == "tool":
        return make_T(T[:3, :3] @ dR, T[:3, 3] + T[:3, :3] @ v * horizon_s)
    return make_T(dR @ T[:3, :3], T[:3, 3] + v * horizon_s)


def twist_change(v: NDArray[np.float64], ref: NDArray[np.float64], dt_s: float
                 ) -> tuple[float, float]:
    """``(linear mm/s^2, angular rad/s^2)``: how fast a twist changes from ``ref`` in ``dt_s``."""
    return (float(np.linalg.norm(v[:3] - ref[:3])) / dt_s,
            float(np.linalg.norm(v[3:] - ref[3:])) / dt_s)


def servo_change_ok(dv_mm_s2: float, dw_rad_s2: float, accel_mm_s2: float,
                    accel_rad_s2: float) -> bool:
    """A tick's change within both accelerations, with ``SERVO_ACCEL_MARGIN`` for the tick
    timing jitter between the law and the guard."""
    return (dv_mm_s2 <= accel_mm_s2 * SERVO_ACCEL_MARGIN
            and dw_rad_s2 <= accel_rad_s2 * SERVO_ACCEL_MARGIN)


def servo_ahead(T: Matrix4, twist: NDArray[np.float64], accel_mm_s2: float,
                watchdog_s: float, accel_rad_s2: float | None = None) -> Matrix4:
    """Where a streamed twist leads in the worst case: held until the watchdog fires, then
    braked at ``accel_mm_s2`` and ``accel_rad_s2`` (None: ``accel_mm_s2 / 1000``),
    translation and rotation each over its own braking time."""
    alpha = accel_mm_s2 / 1000.0 if accel_rad_s2 is None else accel_rad_s2
    v, w = twist[:3], twist[3:]
    t_lin = watchdog_s + float(np.linalg.norm(v)) / (2.0 * accel_mm_s2)
    t_rot = watchdog_s + float(np.linalg.norm(w)) / (2.0 * alpha)
    dR = Rotation.from_rotvec(w * t_rot).as_matrix()
    return make_T(dR @ T[:3, :3], T[:3, 3] + v * t_lin)
