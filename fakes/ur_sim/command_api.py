"""The motion-command half of the simulated controller's API: moves, streams and stops.

Each method validates its input and raises a typed :class:`~fakes.ur_sim.state.EngineError`
BEFORE anything moves; an accepted command is installed as the arm's active command and
returns its id at once, the cycle thread executes it. Stops are always accepted. Units are
UR's wire units (m, rad, m/s, rad/s), so the protocol layer passes values through unchanged.
"""

from __future__ import annotations

import math
import time
from collections.abc import Sequence

import numpy as np

from fakes.ur_sim.arm_core import ArmCore
from fakes.ur_sim.commands import MoveL, PathMove, Servo, SpeedJ, SpeedL
from fakes.ur_sim.planning import MotionPlanner
from fakes.ur_sim.profiles import BlendedLinearPath
from fakes.ur_sim.safety import LIMIT_MARGIN, SafetySupervisor
from fakes.ur_sim.state import (
    CYCLE_S,
    CommandOutcome,
    CommandRejectedError,
    JogFeature,
    PathEntry,
    Vec,
    as_vector,
    positive_number,
)


class CommandAPI:
    """Motion commands of one arm (the base of :class:`~fakes.ur_sim.engine.MotionEngine`).
    All public methods are thread-safe."""

    def __init__(self, core: ArmCore, safety: SafetySupervisor, planner: MotionPlanner
                 ) -> None:
        self._core = core
        self._limits = core.limits
        self._cond = core.cond
        self._safety = safety
        self._planner = planner
        self._servo_ik: tuple[Vec, Vec] | None = None  # last servol pose and its IK

    # -- profiled moves ---------------------------------------------------------------------
    def move_j(self, q_rad: Sequence[float], speed_rad_s: float, accel_rad_s2: float) -> int:
        """Synchronised trapezoidal joint move; returns the command id."""
        q1 = as_vector(q_rad, 6, "target q")
        v = positive_number(speed_rad_s, "joint speed", self._limits.max_joint_speed_rad_s)
        a = positive_number(accel_rad_s2, "joint acceleration", self._limits.max_joint_accel_rad_s2)
        with self._cond:
            self._safety.require_motion_allowed()
            q0, brake = self._core.rest_start(a)
            cmd = self._planner.plan_j(q0, q1, v, a, self._core.new_id(), "movej")
            return self._core.install(cmd, brake)

    def move_j_ik(self, pose6: Sequence[float], speed_rad_s: float, accel_rad_s2: float) -> int:
        """Joint move to the IK solution of a TCP pose nearest the current q (URScript movej(p))."""
        p = as_vector(pose6, 6, "target pose")
        v = positive_number(speed_rad_s, "joint speed", self._limits.max_joint_speed_rad_s)
        a = positive_number(accel_rad_s2, "joint acceleration", self._limits.max_joint_accel_rad_s2)
        with self._cond:
            self._safety.require_motion_allowed()
            q0, brake = self._core.rest_start(a)
            q1 = self._core.ik(p, q0)
            cmd = self._planner.plan_j(q0, q1, v, a, self._core.new_id(), "movej")
            return self._core.install(cmd, brake)

    def move_l(self, pose6: Sequence[float], speed_m_s: float, accel_m_s2: float) -> int:
        """Straight-line TCP move (orientation by slerp); returns the command id.

        The whole line is checked through inverse kinematics first (reach, joint limits,
        singularities). A speed above the tool speed limit trips a protective stop.
        """
        p = as_vector(pose6, 6, "target pose")
        v = positive_number(speed_m_s, "tool speed")
        a = positive_number(accel_m_s2, "tool acceleration", self._limits.max_tcp_accel_m_s2)
        with self._cond:
            self._safety.require_motion_allowed()
            q0, brake = self._core.rest_start(a)
            prof, _ = self._planner.plan_l(q0, p, v, a)
            cmd = MoveL(self._core.new_id(), "movel", BlendedLinearPath([prof], []))
            return self._core.install(cmd, brake)

    def move_path(self, path: Sequence[PathEntry]) -> int:
        """Run waypoints in order; ``async_progress`` is the index of the entry under way.

        Consecutive ``movel`` entries with a blend radius (m, at most half of either
        neighbouring segment) round their corner without stopping; other corners are stop
        points. All segments are planned and checked before the arm moves.
        """
        if not path:
            raise CommandRejectedError("empty path")
        with self._cond:
            self._safety.require_motion_allowed()
            cid = self._core.new_id()
            q, brake = self._core.rest_start(1.0)
            segments = self._planner.plan_path(cid, q, path)
            return self._core.install(PathMove(cid, segments), brake)

    # -- streamed motion ---------------------------------------------------------------------
    def _expiry(self, time_s: float) -> float | None:
        t = float(time_s)
        if not math.isfinite(t):
            raise CommandRejectedError(f"time must be finite, got {time_s!r}")
        with self._cond:
            self._core.sync_idle_clock()
            return self._core.now() + t if t > 0 else None

    def speed_j(self, qd_rad_s: Sequence[float], accel_rad_s2: float, time_s: float = 0.0
                ) -> int:
        """Joint velocity. Brakes with ``accel`` when no new command arrives within ``time_s``
        (``time_s <= 0``: runs until :meth:`speed_stop` or another command)."""
        qd = as_vector(qd_rad_s, 6, "joint speeds")
        a = positive_number(accel_rad_s2, "joint acceleration", self._limits.max_joint_accel_rad_s2)
        expire = self._expiry(time_s)
        with self._cond:
            self._safety.require_motion_allowed()
            if float(np.max(np.abs(qd))) > self._limits.max_joint_speed_rad_s:
                self._safety.trip("speedj above the joint speed limit")
            cmd = SpeedJ(self._core.new_id(), self._core.qd, qd, a, expire)
            return self._core.install(cmd)

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
        a = positive_number(accel_m_s2, "tool acceleration", self._limits.max_tcp_accel_m_s2)
        expire = self._expiry(time_s)
        with self._cond:
            self._safety.require_motion_allowed()
            if float(np.linalg.norm(twist[:3])) > self._limits.max_tcp_speed_m_s:
                self._safety.trip(f"{name} above the tool speed limit")
            target = np.concatenate([twist[:3] * 1000.0, twist[3:]])
            cmd = SpeedL(self._core.new_id(), name, self._core.step_context(), target, frame,
                         a * 1000.0, a, expire)
            return self._core.install(cmd)

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
            self._safety.require_motion_allowed()
            cached = self._servo_ik
            if cached is not None and np.array_equal(cached[0], p):
                q = cached[1]  # the program re-issues the same target every cycle
            else:
                q = self._core.ik(p, self._core.q)
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
        self._safety.require_motion_allowed()
        self._safety.check_joint_limits(q, "servo target")
        t = max(t, CYCLE_S)
        now, host_s = self._core.now(), time.monotonic()
        cmd = self._core.cmd
        # a braking servo of the same stream resumes (its stream history stays): after a host
        # stall the arm may have fallen behind the stream, which is no jump of the stream
        fresh = not (isinstance(cmd, Servo) and cmd.name == name)
        servo = Servo(self._core.new_id(), name, self._core.q, decel=10.0) if fresh else cmd
        assert isinstance(servo, Servo)
        v = servo.stream_velocity(q, t, host_s)
        if float(np.max(np.abs(v))) > self._limits.max_joint_speed_rad_s * LIMIT_MARGIN:
            self._safety.trip(f"{name} target needs more than the joint speed limit "
                              f"({float(np.max(np.abs(v))):.2f} rad/s)")
        servo.retarget(q, t, float(lookahead_s), float(gain), now, host_s)
        if fresh:
            self._core.install(servo)
        return servo.id

    # -- stops (always accepted) ---------------------------------------------------------------
    def speed_stop(self, decel: float = 10.0) -> None:
        """End speedj/speedl/jog with ``decel`` (rad/s^2 or m/s^2); other motion brakes too."""
        d = positive_number(decel, "deceleration")
        with self._cond:
            cmd = self._core.cmd
            now = self._core.now()
            if isinstance(cmd, SpeedJ):
                cmd.stop(d, now)
            elif isinstance(cmd, SpeedL):
                cmd.stop(d * 1000.0, now)
            elif cmd is not None:
                self._core.brake_now(d, "stop", CommandOutcome.PREEMPTED)

    def servo_stop(self, decel: float = 10.0) -> None:
        self.stop_j(decel)

    def stop_j(self, decel_rad_s2: float = 2.0) -> None:
        """Brake in joint space with ``decel``, ending any command."""
        d = positive_number(decel_rad_s2, "deceleration")
        with self._cond:
            cmd = self._core.cmd
            if cmd is not None and cmd.name not in ("protective_stop", "emergency_stop"):
                self._core.brake_now(d, "stopj", CommandOutcome.PREEMPTED)

    def stop_l(self, decel_m_s2: float = 10.0) -> None:
        """Brake so that the TCP decelerates at about ``decel``, ending any command."""
        d = positive_number(decel_m_s2, "deceleration")
        with self._cond:
            cmd = self._core.cmd
            if cmd is None or cmd.name in ("protective_stop", "emergency_stop"):
                return
            twist = self._core.kin.jacobian_tcp(self._core.q) @ self._core.qd
            v = max(float(np.linalg.norm(twist[:3])) / 1000.0, 1e-9)
            peak = float(np.max(np.abs(self._core.qd)))
            t_stop = v / d
            joint_decel = peak / t_stop if t_stop > 0 else d
            self._core.brake_now(max(joint_decel, 1e-6), "stopl", CommandOutcome.PREEMPTED)
