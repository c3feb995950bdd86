"""Time-parametrised velocity profiles for the simulated controller's moves.

A UR controller plans ``movej`` as a synchronised trapezoid (all joints start and arrive
together, the leading joint honouring speed and acceleration) and ``movel`` as a trapezoid
along the straight line with the orientation interpolated alongside. Profiles here are pure
functions of time so the engine can evaluate them at whatever instant its real-time loop wakes,
and they land exactly on the target at ``duration_s``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.spatial.transform import Rotation

from estimator.transforms import make_T


@dataclass(frozen=True)
class Trapezoid:
    """Scalar 0 -> ``distance`` with at most ``v_max`` and ``a_max``, from and to rest.

    Becomes triangular when the distance is too short to reach ``v_max``.
    """

    distance: float
    v_max: float
    a_max: float
    t_acc_s: float = field(init=False)
    t_flat_s: float = field(init=False)
    v_peak: float = field(init=False)

    def __post_init__(self) -> None:
        if not (self.v_max > 0 and self.a_max > 0) or self.distance < 0:
            raise ValueError("trapezoid needs v_max > 0, a_max > 0, distance >= 0")
        d, v, a = self.distance, self.v_max, self.a_max
        if d * a >= v * v:
            t_acc, v_peak = v / a, v
            t_flat = (d - v * v / a) / v
        else:
            v_peak = math.sqrt(d * a)
            t_acc, t_flat = v_peak / a, 0.0
        object.__setattr__(self, "t_acc_s", t_acc)
        object.__setattr__(self, "t_flat_s", t_flat)
        object.__setattr__(self, "v_peak", v_peak)

    @property
    def duration_s(self) -> float:
        return 2.0 * self.t_acc_s + self.t_flat_s

    def at(self, t_s: float) -> tuple[float, float, float]:
        """(position, velocity, acceleration) at ``t_s`` (clamped to [0, duration])."""
        a, v, ta, tf = self.a_max, self.v_peak, self.t_acc_s, self.t_flat_s
        T = self.duration_s
        if t_s <= 0.0:
            return 0.0, 0.0, 0.0
        if t_s >= T:
            return self.distance, 0.0, 0.0
        if t_s < ta:
            return 0.5 * a * t_s * t_s, a * t_s, a
        if t_s < ta + tf:
            return 0.5 * a * ta * ta + v * (t_s - ta), v, 0.0
        tr = T - t_s
        return self.distance - 0.5 * a * tr * tr, a * tr, -a


class JointProfile:
    """Straight line in joint space; the joint with the largest travel sets the timing."""

    def __init__(self, q0: ArrayLike, q1: ArrayLike, speed_rad_s: float,
                 accel_rad_s2: float) -> None:
        self.q0 = np.asarray(q0, dtype=float).reshape(-1)
        self.q1 = np.asarray(q1, dtype=float).reshape(-1)
        delta = self.q1 - self.q0
        lead = float(np.max(np.abs(delta))) if delta.size else 0.0
        self._dir = delta / lead if lead > 0 else np.zeros_like(delta)
        self._trap = Trapezoid(lead, speed_rad_s, accel_rad_s2)

    @property
    def duration_s(self) -> float:
        return self._trap.duration_s

    def at(self, t_s: float) -> tuple[NDArray[np.float64], NDArray[np.float64],
                                       NDArray[np.float64]]:
        """(q, qd, qdd) at ``t_s``; exactly ``q1`` from ``duration_s`` on."""
        if t_s >= self.duration_s:
            z = np.zeros_like(self.q1)
            return self.q1.copy(), z, z.copy()
        s, sd, sdd = self._trap.at(t_s)
        return self.q0 + s * self._dir, sd * self._dir, sdd * self._dir


class LinearProfile:
    """Straight TCP line (mm) with the orientation slerped on the same normalised progress.

    Translation honours ``speed``/``accel`` (mm/s, mm/s^2); rotation honours
    ``rot_speed``/``rot_accel`` (rad/s, rad/s^2), so a pure re-orientation still takes time.
    """

    def __init__(self, T0: ArrayLike, T1: ArrayLike, speed_mm_s: float, accel_mm_s2: float,
                 rot_speed_rad_s: float, rot_accel_rad_s2: float) -> None:
        self.T0 = np.asarray(T0, dtype=float).reshape(4, 4)
        self.T1 = np.asarray(T1, dtype=float).reshape(4, 4)
        self.p0 = self.T0[:3, 3]
        self.delta_mm = self.T1[:3, 3] - self.p0
        self.length_mm = float(np.linalg.norm(self.delta_mm))
        rots = Rotation.from_matrix(np.stack([self.T0[:3, :3], self.T1[:3, :3]]))
        self._R0 = rots[0]
        # Slerp as R0 * exp(u * log(R0^-1 R1)): the same geodesic scipy's Slerp follows
        # (the tests check they agree), at a fifth of its per-call cost at 500 Hz.
        self._rotvec = (rots[0].inv() * rots[1]).as_rotvec()
        self.angle_rad = float(np.linalg.norm(self._rotvec))
        # Limits on the normalised progress u in [0, 1], the tighter of both motions.
        v_u, a_u = math.inf, math.inf
        if self.length_mm > 0:
            v_u, a_u = speed_mm_s / self.length_mm, accel_mm_s2 / self.length_mm
        if self.angle_rad > 0:
            v_u = min(v_u, rot_speed_rad_s / self.angle_rad)
            a_u = min(a_u, rot_accel_rad_s2 / self.angle_rad)
        self._moves = math.isfinite(v_u)
        self._trap = Trapezoid(1.0 if self._moves else 0.0,
                               v_u if self._moves else 1.0, a_u if self._moves else 1.0)

    @property
    def duration_s(self) -> float:
        return self._trap.duration_s

    @property
    def ramp_s(self) -> float:
        """Duration of the acceleration (= deceleration) phase."""
        return self._trap.t_acc_s

    @property
    def rotvec_rad(self) -> NDArray[np.float64]:
        """Rotation from start to end, in the start frame."""
        return self._rotvec.copy()

    def progress(self, t_s: float) -> tuple[float, float]:
        """(u, du/dt) at ``t_s``."""
        u, ud, _ = self._trap.at(t_s)
        return (u, ud) if self._moves else (1.0, 0.0)

    def pose_at_progress(self, u: float) -> NDArray[np.float64]:
        if u >= 1.0:
            return self.T1.copy()
        R = (self._R0 * Rotation.from_rotvec(u * self._rotvec)).as_matrix()
        return make_T(R, self.p0 + u * self.delta_mm)

    def at(self, t_s: float) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """(T_base_tcp in mm, twist [v mm/s, w rad/s]) at ``t_s``."""
        u, ud = self.progress(t_s)
        twist = np.zeros(6)
        if self._moves and ud > 0:
            twist[:3] = ud * self.delta_mm
            rotvec = (Rotation.from_matrix(self.T1[:3, :3])
                      * Rotation.from_matrix(self.T0[:3, :3]).inv()).as_rotvec()
            twist[3:] = ud * rotvec
        return self.pose_at_progress(u), twist


class BlendedLinearPath:
    """Consecutive straight TCP moves, each corner rounded within its blend radius.

    The next move starts while the previous one is still decelerating (once the previous is
    within its blend radius of the corner) and the two displacements add up: velocities
    superpose, so the TCP sweeps a smooth curve past the corner without stopping. The overlap
    never exceeds the deceleration ramp of the first nor the acceleration ramp of the second,
    so with equal accelerations the speed never exceeds either move's speed. With no blends it
    is the moves one after the other, stopping at each corner; it always ends exactly on the
    last target.
    """

    def __init__(self, moves: list[LinearProfile], blends_mm: list[float]) -> None:
        if not moves or len(blends_mm) != len(moves) - 1:
            raise ValueError("need n moves and n - 1 blend radii")
        self.moves = moves
        self.T_start = moves[0].T0.copy()
        self._R_start = Rotation.from_matrix(self.T_start[:3, :3])
        starts = [0.0]
        for i, blend in enumerate(blends_mm):
            a, b = moves[i], moves[i + 1]
            overlap = 0.0
            if blend > 0 and a.length_mm > 0:
                frac = max(0.0, 1.0 - blend / a.length_mm)
                overlap = min(a.duration_s - _time_of_progress(a, frac), a.ramp_s, b.ramp_s)
            starts.append(starts[-1] + a.duration_s - overlap)
        self.starts_s = starts
        self.duration_s = starts[-1] + moves[-1].duration_s

    def index_at(self, t_s: float) -> int:
        """Index of the latest move that has started at ``t_s``."""
        return max(i for i, t0 in enumerate(self.starts_s) if t0 <= max(t_s, 0.0))

    def pose_at(self, t_s: float) -> NDArray[np.float64]:
        if t_s >= self.duration_s:
            return self.moves[-1].T1.copy()
        p = self.T_start[:3, 3].copy()
        R = self._R_start
        for move, t0 in zip(self.moves, self.starts_s, strict=True):
            if t_s <= t0:
                break
            u, _ = move.progress(t_s - t0)
            p += u * move.delta_mm
            R = R * Rotation.from_rotvec(u * move.rotvec_rad)
        return make_T(R.as_matrix(), p)


def _time_of_progress(move: LinearProfile, u: float) -> float:
    """When a move reaches progress ``u`` (bisection: the profile is monotone)."""
    lo, hi = 0.0, move.duration_s
    for _ in range(60):
        mid = 0.5 * (lo + hi)
        if move.progress(mid)[0] < u:
            lo = mid
        else:
            hi = mid
    return hi
