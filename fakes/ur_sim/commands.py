"""What the simulated arm can be doing: one class per kind of motion command.

Each command advances itself to ``now`` from the engine's state in :meth:`Command.step`; the
engine owns the state, the safety checks and the thread.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
from scipy.spatial.transform import Rotation

from fakes.ur_sim.kinematics import UnreachableError
from fakes.ur_sim.profiles import BlendedLinearPath, JointProfile
from fakes.ur_sim.state import CYCLE_S, JogFeature, Vec

if TYPE_CHECKING:
    from fakes.ur_sim.engine import MotionEngine


class SafetyTrip(Exception):
    """Raised inside a step when the motion itself cannot continue (e.g. IK lost)."""


@dataclass
class Step:
    q: Vec
    qd: Vec
    qdd: Vec
    done: bool


class Command:
    """One thing the arm is doing. ``step`` advances it to ``now`` from the engine state."""

    limited = True  # subject to the run-time safety checks (brakes are not)

    def __init__(self, cid: int, name: str) -> None:
        self.id = cid
        self.name = name
        self.progress = -1

    def step(self, eng: MotionEngine, now: float, dt: float) -> Step:
        raise NotImplementedError


class Brake(Command):
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

    def step(self, eng: MotionEngine, now: float, dt: float) -> Step:
        self.t += dt
        if self.t >= self.T:
            z = np.zeros(6)
            return Step(self.q_end, z, z.copy(), True)
        t, T = self.t, self.T
        return Step(self.q0 + self.qd0 * t - 0.5 * self.qd0 / T * t * t,
                     self.qd0 * (1.0 - t / T), -self.qd0 / T, False)


class Then(Command):
    """``first`` then ``second``: a profiled move commanded while the arm still moves brakes
    first, because a trapezoid starts from rest."""

    def __init__(self, first: Brake, second: Command) -> None:
        super().__init__(second.id, second.name)
        self.first, self.second = first, second
        self.limited = True

    def step(self, eng: MotionEngine, now: float, dt: float) -> Step:
        if self.first is not None and self.first.t < self.first.T:
            out = self.first.step(eng, now, dt)
            out.done = False
            return out
        out = self.second.step(eng, now, dt)
        self.progress = self.second.progress
        return out


class MoveJ(Command):
    def __init__(self, cid: int, name: str, profile: JointProfile) -> None:
        super().__init__(cid, name)
        self.profile = profile
        self.tau = 0.0
        self.progress = 0

    def step(self, eng: MotionEngine, now: float, dt: float) -> Step:
        f = eng._speed_fraction
        self.tau += dt * f
        q, qd, qdd = self.profile.at(self.tau)
        return Step(q, qd * f, qdd * f * f, self.tau >= self.profile.duration_s)


class MoveL(Command):
    """Straight (or blended) TCP motion; joints follow by IK from the previous cycle."""

    def __init__(self, cid: int, name: str, path: BlendedLinearPath, first_entry: int = 0
                 ) -> None:
        super().__init__(cid, name)
        self.path = path
        self.tau = 0.0
        self.first_entry = first_entry
        self.progress = first_entry

    def step(self, eng: MotionEngine, now: float, dt: float) -> Step:
        self.tau += dt * eng._speed_fraction
        done = self.tau >= self.path.duration_s
        self.progress = self.first_entry + self.path.index_at(self.tau)
        T = self.path.pose_at(self.tau)
        try:
            # the closed form lands the final pose exactly; Newton is plenty in between
            q = (eng._kin.inverse_tcp(T, eng._q) if done
                 else eng._kin.inverse_tcp_local(T, eng._q, eng._q + eng._qd * dt))
        except UnreachableError as err:
            raise SafetyTrip("linear move lost its inverse kinematics") from err
        qd = (q - eng._q) / dt if dt > 0 else np.zeros(6)
        return Step(q, qd, (qd - eng._qd) / dt if dt > 0 else np.zeros(6), done)


class PathMove(Command):
    def __init__(self, cid: int, segments: list[Command]) -> None:
        super().__init__(cid, "path")
        self.segments = segments
        self.index = 0
        self.progress = 0

    def step(self, eng: MotionEngine, now: float, dt: float) -> Step:
        seg = self.segments[self.index]
        out = seg.step(eng, now, dt)
        self.progress = seg.progress
        if out.done and self.index + 1 < len(self.segments):
            self.index += 1
            out.done = False
        return out


class SpeedJ(Command):
    """Ramp the joint velocity vector to a target; after ``expire_at`` the target is zero."""

    def __init__(self, cid: int, qd0: Vec, target: Vec, accel: float,
                 expire_at: float | None) -> None:
        super().__init__(cid, "speedj")
        self.qd = qd0.copy()
        self.target, self.accel, self.expire_at = target, accel, expire_at

    def stop(self, decel: float, now: float) -> None:
        self.accel, self.expire_at = decel, now

    def step(self, eng: MotionEngine, now: float, dt: float) -> Step:
        stopping = self.expire_at is not None and now >= self.expire_at
        target = np.zeros(6) if stopping else self.target
        dv = target - self.qd
        m = float(np.max(np.abs(dv)))
        new = self.qd + dv * min(1.0, self.accel * dt / m) if m > 0 else self.qd.copy()
        q = eng._q + 0.5 * (self.qd + new) * dt
        qdd = (new - self.qd) / dt if dt > 0 else np.zeros(6)
        self.qd = new
        return Step(q, new.copy(), qdd, stopping and not np.any(new))


class SpeedL(Command):
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

    def step(self, eng: MotionEngine, now: float, dt: float) -> Step:
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
            raise SafetyTrip("Cartesian speed command left the reachable workspace") from err
        self.T, self.twist = T, new
        qd = (q - eng._q) / dt if dt > 0 else np.zeros(6)
        return Step(q, qd, (qd - eng._qd) / dt if dt > 0 else np.zeros(6),
                     stopping and not np.any(new))


class Servo(Command):
    """Go to the latest target within its ``time_s``; brake when the stream dries up."""

    def __init__(self, cid: int, name: str, decel: float) -> None:
        super().__init__(cid, name)
        self.decel = decel
        self.q_from = np.zeros(6)
        self.q_to = np.zeros(6)
        self.t_cmd = 0.0
        self.time_s = CYCLE_S
        self.brake: Brake | None = None

    def retarget(self, q_now: Vec, q_to: Vec, time_s: float, now: float) -> None:
        self.q_from, self.q_to, self.t_cmd, self.time_s = q_now.copy(), q_to, now, time_s
        self.brake = None

    @property
    def velocity(self) -> Vec:
        return (self.q_to - self.q_from) / self.time_s

    def step(self, eng: MotionEngine, now: float, dt: float) -> Step:
        if self.brake is None and now > self.t_cmd + self.time_s + eng.limits.servo_watchdog_s:
            self.brake = Brake(self.id, self.name, eng._q, eng._qd, self.decel)
        if self.brake is not None:
            return self.brake.step(eng, now, dt)
        elapsed = now - self.t_cmd
        if elapsed >= self.time_s:
            z = np.zeros(6)
            return Step(self.q_to.copy(), z, (z - eng._qd) / dt if dt > 0 else z, False)
        v = self.velocity
        return Step(self.q_from + v * elapsed, v, (v - eng._qd) / dt if dt > 0 else v * 0,
                     False)
