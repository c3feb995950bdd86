"""What the simulated arm can be doing: one class per kind of motion command.

Each command advances itself to ``now`` in :meth:`Command.step` from a read-only
:class:`~fakes.ur_sim.step_context.StepContext` of the arm; the engine owns the state, the
safety checks and the thread, and commands know nothing of it.
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation

from fakes.ur_sim.kinematics import UnreachableError
from fakes.ur_sim.profiles import BlendedLinearPath, JointProfile
from fakes.ur_sim.state import CYCLE_S, JogFeature, Vec
from fakes.ur_sim.step_context import StepContext


class SafetyTrip(Exception):
    """Raised inside a step when the motion itself cannot continue (e.g. IK lost)."""


@dataclass
class Step:
    q: Vec
    qd: Vec
    qdd: Vec
    done: bool


class Command:
    """One thing the arm is doing. ``step`` advances it to ``now`` from the arm's state."""

    limited = True  # subject to the run-time safety checks (brakes are not)

    def __init__(self, cid: int, name: str) -> None:
        self.id = cid
        self.name = name
        self.progress = -1

    def step(self, ctx: StepContext, now: float, dt: float) -> Step:
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

    def step(self, ctx: StepContext, now: float, dt: float) -> Step:
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

    def step(self, ctx: StepContext, now: float, dt: float) -> Step:
        if self.first is not None and self.first.t < self.first.T:
            out = self.first.step(ctx, now, dt)
            out.done = False
            return out
        out = self.second.step(ctx, now, dt)
        self.progress = self.second.progress
        return out


class MoveJ(Command):
    def __init__(self, cid: int, name: str, profile: JointProfile) -> None:
        super().__init__(cid, name)
        self.profile = profile
        self.tau = 0.0
        self.progress = 0

    def step(self, ctx: StepContext, now: float, dt: float) -> Step:
        f = ctx.speed_fraction
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

    def step(self, ctx: StepContext, now: float, dt: float) -> Step:
        self.tau += dt * ctx.speed_fraction
        done = self.tau >= self.path.duration_s
        self.progress = self.first_entry + self.path.index_at(self.tau)
        T = self.path.pose_at(self.tau)
        try:
            # the closed form lands the final pose exactly; Newton is plenty in between
            q = (ctx.kin.inverse_tcp(T, ctx.q) if done
                 else ctx.kin.inverse_tcp_local(T, ctx.q, ctx.q + ctx.qd * dt))
        except UnreachableError as err:
            raise SafetyTrip("linear move lost its inverse kinematics") from err
        qd = (q - ctx.q) / dt if dt > 0 else np.zeros(6)
        return Step(q, qd, (qd - ctx.qd) / dt if dt > 0 else np.zeros(6), done)


class PathMove(Command):
    def __init__(self, cid: int, segments: list[Command]) -> None:
        super().__init__(cid, "path")
        self.segments = segments
        self.index = 0
        self.progress = 0

    def step(self, ctx: StepContext, now: float, dt: float) -> Step:
        seg = self.segments[self.index]
        out = seg.step(ctx, now, dt)
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

    def step(self, ctx: StepContext, now: float, dt: float) -> Step:
        stopping = self.expire_at is not None and now >= self.expire_at
        target = np.zeros(6) if stopping else self.target
        dv = target - self.qd
        m = float(np.max(np.abs(dv)))
        new = self.qd + dv * min(1.0, self.accel * dt / m) if m > 0 else self.qd.copy()
        q = ctx.q + 0.5 * (self.qd + new) * dt
        qdd = (new - self.qd) / dt if dt > 0 else np.zeros(6)
        self.qd = new
        return Step(q, new.copy(), qdd, stopping and not np.any(new))


class SpeedL(Command):
    """Cartesian velocity (base or tool frame) integrated on the TCP pose, joints by IK."""

    def __init__(self, cid: int, name: str, ctx: StepContext, target: Vec, frame: JogFeature,
                 accel_mm_s2: float, accel_rad_s2: float, expire_at: float | None) -> None:
        super().__init__(cid, name)
        self.T = ctx.kin.forward_tcp(ctx.q)
        self.twist = ctx.kin.jacobian_tcp(ctx.q) @ ctx.qd
        self.target, self.frame = target, frame
        self.acc_lin, self.acc_rot, self.expire_at = accel_mm_s2, accel_rad_s2, expire_at

    def stop(self, decel_mm_s2: float, now: float) -> None:
        self.acc_lin, self.acc_rot, self.expire_at = decel_mm_s2, decel_mm_s2 / 1000.0, now

    @staticmethod
    def _ramp(cur: Vec, target: Vec, accel: float, dt: float) -> Vec:
        dv = target - cur
        m = float(np.linalg.norm(dv))
        return cur + dv * min(1.0, accel * dt / m) if m > 0 else cur.copy()

    def step(self, ctx: StepContext, now: float, dt: float) -> Step:
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
            q = ctx.kin.inverse_tcp_local(T, ctx.q, ctx.q + ctx.qd * dt)
        except UnreachableError as err:
            raise SafetyTrip("Cartesian speed command left the reachable workspace") from err
        self.T, self.twist = T, new
        qd = (q - ctx.q) / dt if dt > 0 else np.zeros(6)
        return Step(q, qd, (qd - ctx.qd) / dt if dt > 0 else np.zeros(6),
                     stopping and not np.any(new))


STREAM_WINDOW_S = 0.02  # servo stream speed is judged over at least this much host time


class Servo(Command):
    """servoj/servol: follow a stream of joint targets on the controller clock.

    Each new target starts a reference segment from the present reference to the target, run
    at the speed the stream implies: the step from the previous target over the time the stream
    took to deliver it (at least the command's ``time``), so a stream delayed by a host stall
    does not read as a jump. The arm follows the reference with a proportional law, velocity =
    reference velocity + (reference - q) / tau with tau = lookahead_time * 100 / gain (at least
    two cycles): a longer lookahead smooths and lags more, a higher gain follows tighter and
    overshoots more, as UR describes the two parameters. Acceleration is limited to the arm's
    joint acceleration and speed to its joint speed; the arm brakes when the stream stops.
    """

    def __init__(self, cid: int, name: str, q_arm: Vec, decel: float) -> None:
        super().__init__(cid, name)
        self.decel = decel
        self.ref = q_arm.copy()
        self.target = q_arm.copy()
        self.v_ref = np.zeros(6)
        self.seg_left_s = 0.0  # controller time the reference still runs towards the target
        self.last_call_t = 0.0
        self.samples: deque[tuple[float, Vec]] = deque()  # (host time, target) seen
        self.time_s = CYCLE_S
        self.tau_s = 0.033
        self.brake: Brake | None = None

    def stream_velocity(self, q_to: Vec, time_s: float, host_s: float) -> Vec:
        """Joint velocity the stream asks for with this target (the safety check): the step
        from a target seen at least ``STREAM_WINDOW_S`` earlier over the time between them.

        A client that stalls and then catches up sends several targets in a burst, of which
        a controller cycle sees only the last; over the window the burst averages out to the
        stream's real speed, while a target that jumps truly too far still shows.
        """
        if not self.samples:
            return (q_to - self.target) / time_s
        t_ref, q_ref = self.samples[0]
        newer = len(self.samples)  # targets after the reference, this one included
        for i in range(len(self.samples) - 1, -1, -1):
            t, q = self.samples[i]
            if t <= host_s - STREAM_WINDOW_S:
                t_ref, q_ref, newer = t, q, len(self.samples) - i
                break
        # each target asks for its own ``time``: n targets span at least n * time
        return (q_to - q_ref) / max(time_s * newer, host_s - t_ref)

    def retarget(self, q_to: Vec, time_s: float, lookahead_s: float, gain: float, now: float,
                 host_s: float) -> None:
        self.last_call_t, self.time_s = now, time_s
        self.tau_s = max(2 * CYCLE_S, lookahead_s * 100.0 / gain)
        self.brake = None
        if self.samples and np.array_equal(q_to, self.target):
            return  # the same target again: the program re-issues it every cycle
        # the reference reaches the target in the time the stream took to deliver it
        interval = max(time_s, host_s - self.samples[-1][0]) if self.samples else time_s
        self.v_ref = (q_to - self.ref) / interval
        self.seg_left_s = interval
        self.target = q_to.copy()
        self.samples.append((host_s, self.target))
        while len(self.samples) > 2 and self.samples[1][0] < host_s - 4 * STREAM_WINDOW_S:
            self.samples.popleft()

    def step(self, ctx: StepContext, now: float, dt: float) -> Step:
        silent_s = now - self.last_call_t - self.time_s
        if self.brake is None and silent_s > ctx.limits.servo_watchdog_s:
            self.brake = Brake(self.id, self.name, ctx.q, ctx.qd, self.decel)
        if self.brake is not None:
            return self.brake.step(ctx, now, dt)
        run_s = min(dt, self.seg_left_s)
        if run_s > 0:
            self.seg_left_s -= run_s
            self.ref = self.target.copy() if self.seg_left_s <= 1e-9 else (
                self.ref + self.v_ref * run_s)
        v_ref = self.v_ref * (run_s / dt)
        v_cmd = v_ref + (self.ref - ctx.q) / self.tau_s
        dv = v_cmd - ctx.qd
        dv_max = ctx.limits.max_joint_accel_rad_s2 * dt
        m = float(np.max(np.abs(dv)))
        if m > dv_max:
            dv *= dv_max / m
        qd = ctx.qd + dv
        peak = float(np.max(np.abs(qd)))
        if peak > ctx.limits.max_joint_speed_rad_s:
            qd *= ctx.limits.max_joint_speed_rad_s / peak
        q = ctx.q + 0.5 * (ctx.qd + qd) * dt
        return Step(q, qd, (qd - ctx.qd) / dt, False)
