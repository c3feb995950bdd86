"""The position-based visual servo law: a base-frame TCP twist from the pose error.

Pure maths, no arm and no camera, so it is unit-tested on its own. The error is between the
TCP goal (moving with the target) and the TCP, both in the base frame:
``e_p = p_goal - p_tcp`` and ``e_r = log(R_goal R_tcp^T)`` (rotation vector, base frame). The
twist is the goal's own velocity (feed-forward, from the target filter) plus an exponential
law ``gain * e``, whose speed is capped three ways: by the configured maximum, by braking room
(the speed ``v`` with ``v * watchdog + v^2 / 2a = |e|``: held until the arm's watchdog would
fire and then braked, it still stops at the goal, so it never overshoots and never leads the
guard's look-ahead past the goal) and by the acceleration from the previous tick (the
commanded twist never jumps). Translation and rotation have their own acceleration: a tool
turn is limited by the wrist joints, not by how fast the TCP may gather speed.

Braking room is planned at ``BRAKE_SHARE`` of the acceleration the per-tick rate limit allows:
the rate limit grants at most one nominal tick's change per tick, and ticks come later than
nominal (sleep granularity, a loaded host), so the acceleration actually reached is lower.
Planned at the full value, the commanded speed fell behind the braking curve on every long
deceleration and overshot the goal (measured: 7 deg past a 104 deg turn).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray
from scipy.spatial.transform import Rotation

Matrix4 = NDArray[np.float64]
Vec = NDArray[np.float64]


@dataclass(frozen=True)
class LawParams:
    gain_lin_per_s: float  # 1/s: the exponential rate of the translation error
    gain_rot_per_s: float  # 1/s: the same for the rotation error
    max_speed_mm_s: float
    max_angular_speed_rad_s: float
    accel_mm_s2: float  # linear
    watchdog_s: float = 0.0  # how long the arm keeps a twist when ticks stop
    # angular; None: accel_mm_s2 / 1000 rad/s^2 (UR's rule for speedl's aRot)
    angular_accel_rad_s2: float | None = None

    @property
    def accel_rad_s2(self) -> float:
        a = self.angular_accel_rad_s2
        return self.accel_mm_s2 / 1000.0 if a is None else a


BRAKE_SHARE = 0.75  # braking room is planned at this share of the acceleration (module doc)


def pose_error(T_tcp: Matrix4, T_goal: Matrix4) -> tuple[Vec, Vec]:
    """``(e_p mm, e_r rad)`` in the base frame: the TCP plus that error is the goal."""
    e_p = np.asarray(T_goal[:3, 3] - T_tcp[:3, 3], dtype=float)
    e_r = Rotation.from_matrix(T_goal[:3, :3] @ T_tcp[:3, :3].T).as_rotvec()
    return e_p, np.asarray(e_r, dtype=float)


def goal_velocity(T_base_target: Matrix4, T_goal: Matrix4, v_target_mm_s: Vec,
                  w_target_rad_s: Vec) -> Vec:
    """Twist of a goal rigidly attached to a target moving at ``(v, w)`` (base frame)."""
    lever = T_goal[:3, 3] - T_base_target[:3, 3]
    return np.concatenate([v_target_mm_s + np.cross(w_target_rad_s, lever), w_target_rad_s])


def braking_speed(distance: float, accel: float, watchdog_s: float) -> float:
    """The speed from which holding for ``watchdog_s`` then braking at ``accel`` covers
    exactly ``distance``."""
    return accel * (-watchdog_s + float(np.sqrt(watchdog_s ** 2 + 2.0 * distance / accel)))


def _capped(error: Vec, gain: float, vmax: float, accel: float, watchdog_s: float) -> Vec:
    n = float(np.linalg.norm(error))
    if n < 1e-12:
        return np.zeros(3)
    speed = min(gain * n, vmax, braking_speed(n, accel, watchdog_s))
    return error / n * speed


def _rate_limited(v: Vec, v_prev: Vec, max_step: float) -> Vec:
    dv = v - v_prev
    n = float(np.linalg.norm(dv))
    return v.copy() if n <= max_step else v_prev + dv * (max_step / n)


def pbvs_twist(T_tcp: Matrix4, T_goal: Matrix4, feed_forward: Vec, previous: Vec, dt_s: float,
               p: LawParams) -> Vec:
    """The twist ``[vx, vy, vz mm/s, wx, wy, wz rad/s]`` to command now (see module doc)."""
    e_p, e_r = pose_error(T_tcp, T_goal)
    a_lin, a_rot = p.accel_mm_s2, p.accel_rad_s2
    v = feed_forward[:3] + _capped(e_p, p.gain_lin_per_s, p.max_speed_mm_s,
                                   BRAKE_SHARE * a_lin, p.watchdog_s)
    w = feed_forward[3:] + _capped(e_r, p.gain_rot_per_s, p.max_angular_speed_rad_s,
                                   BRAKE_SHARE * a_rot, p.watchdog_s)
    v = _clip_norm(v, p.max_speed_mm_s)
    w = _clip_norm(w, p.max_angular_speed_rad_s)
    dt = max(float(dt_s), 0.0)
    v = _rate_limited(v, previous[:3], a_lin * dt)
    w = _rate_limited(w, previous[3:], a_rot * dt)
    return np.concatenate([v, w])


def _clip_norm(x: Vec, limit: float) -> Vec:
    n = float(np.linalg.norm(x))
    return x * (limit / n) if n > limit else x


def integrate(integral: Vec, error: Vec, dt_s: float, gain_per_s2: float, limit: float
              ) -> Vec:
    """One step of the integral term (tracking): ``integral + e dt``, clamped so that
    ``gain * integral`` never exceeds ``limit`` (no wind-up). Added to the feed-forward, it
    removes the steady lag an arm that runs a little slower than commanded would leave."""
    out = integral + error * max(dt_s, 0.0)
    n = float(np.linalg.norm(out)) * gain_per_s2
    return out * (limit / n) if n > limit else out
