"""Typed refusals and the checks that produce them, run BEFORE anything is commanded.

Every refusal is a :class:`CellError` with a machine-readable ``code``, a ``kind`` the API
maps to an HTTP status, and a message that tells a person what to do. Checks only read; a
failed check therefore guarantees that nothing moved.
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.spatial.transform import Rotation, Slerp

from cell.config.schema import LimitsConfig
from cell.error_codes import ErrorCode
from cell.errors import LimitError, RefusedError, UnavailableError
from cell.motion.reach import ArmAt, ReachCheck
from cell.vision.frames import tilt_deg
from drivers.arm import ArmState

PATH_STEP_MM = 2.0  # sampling of a commanded path for the envelope and tilt checks
PATH_STEP_DEG = 1.0
_EPS = 1e-6


def linear_path(T_from: ArrayLike, T_goal: ArrayLike, step_mm: float = PATH_STEP_MM,
                step_deg: float = PATH_STEP_DEG) -> list[NDArray[np.float64]]:
    """Poses along a straight TCP move as a UR controller interpolates it (moveL, servoL):
    position along the line, orientation about one fixed axis (slerp), end points included."""
    A = np.asarray(T_from, dtype=float)
    B = np.asarray(T_goal, dtype=float)
    dist = float(np.linalg.norm(B[:3, 3] - A[:3, 3]))
    rots = Rotation.from_matrix(np.stack([A[:3, :3], B[:3, :3]]))
    angle = float(np.degrees((rots[0].inv() * rots[1]).magnitude()))
    n = max(2, int(np.ceil(max(dist / step_mm, angle / step_deg))) + 1)
    s = np.linspace(0.0, 1.0, n)
    R = Slerp([0.0, 1.0], rots)(s).as_matrix()
    out = []
    for k, u in enumerate(s):
        T = np.eye(4)
        T[:3, :3] = R[k]
        T[:3, 3] = A[:3, 3] + u * (B[:3, 3] - A[:3, 3])
        out.append(T)
    return out


class SafetyGuard:
    """The configured limits as checks; stateless apart from the limits.

    The path rule, for every kind of motion (moves, jogs, streamed targets): from a pose
    inside the limits, every pose along the commanded path stays inside; from a pose
    outside (an arm left there by hand, or limits tightened), the path may never make the
    violation worse and must end with it reduced, so an operator can always jog back in but
    never further out. Given where the arm is (``at``), the path is also checked as the arm
    will take it (:class:`cell.motion.reach.ReachCheck`: joints, range, singularities).
    """

    def __init__(self, limits: LimitsConfig, model: str = "ur5e") -> None:
        self.limits = limits
        self.reach = ReachCheck(limits, model)
        self._lo = np.asarray(limits.workspace_min_mm, dtype=float)
        self._hi = np.asarray(limits.workspace_max_mm, dtype=float)

    def in_envelope(self, position_mm: ArrayLike) -> bool:
        return self.box_violation_mm(position_mm) == 0.0

    def box_violation_mm(self, position_mm: ArrayLike) -> float:
        """How far outside the workspace box a TCP position is (0 inside)."""
        p = np.asarray(position_mm, dtype=float).reshape(3)
        out = np.maximum(self._lo - p, 0.0) + np.maximum(p - self._hi, 0.0)
        return float(np.linalg.norm(out))

    def tilt_excess_deg(self, T_base_tcp: ArrayLike) -> float:
        return max(0.0, tilt_deg(T_base_tcp) - self.limits.tilt_limit_deg)

    def check_arm(self, state: ArmState, now_s: float) -> None:
        """The arm can take a motion command now, and its state is fresh."""
        if not state.connected:
            raise UnavailableError(ErrorCode.arm_disconnected,
                                   "the arm is not connected; check the controller and network")
        if state.emergency_stop:
            raise RefusedError(ErrorCode.emergency_stop,
                               "the arm is emergency-stopped; release the e-stop at the cell")
        if state.protective_stop:
            raise RefusedError(ErrorCode.protective_stop,
                               "the arm is protective-stopped; clear the cause, then unlock it "
                               "(page: Unlock, or POST /api/v1/arm/unlock) before moving")
        if not state.ready:
            raise RefusedError(ErrorCode.arm_not_ready,
                               f"the arm is not ready for motion (mode {state.robot_mode}, "
                               f"safety {state.safety_status}); power it on (page: Power, or "
                               "POST /api/v1/arm/power)")
        age = now_s - state.timestamp_s
        if age > self.limits.max_pose_age_s:
            raise RefusedError(ErrorCode.stale_pose,
                               f"the arm's pose is {age:.2f} s old (limit "
                               f"{self.limits.max_pose_age_s} s); the robot state stream stalled")

    def check_speed(self, speed_mm_s: float, accel_mm_s2: float) -> None:
        lim = self.limits
        if not (math.isfinite(speed_mm_s) and lim.min_speed_mm_s <= speed_mm_s
                <= lim.max_speed_mm_s):
            raise LimitError(ErrorCode.speed_limit, f"speed {speed_mm_s} mm/s is outside "
                             f"[{lim.min_speed_mm_s}, {lim.max_speed_mm_s}] mm/s")
        if not (math.isfinite(accel_mm_s2) and 0 < accel_mm_s2 <= lim.max_accel_mm_s2):
            raise LimitError(ErrorCode.accel_limit,
                             f"acceleration {accel_mm_s2} mm/s^2 is outside (0, "
                             f"{lim.max_accel_mm_s2}] mm/s^2")

    def check_joint_speed(self, speed_rad_s: float, accel_rad_s2: float) -> None:
        lim = self.limits
        v, a = math.degrees(speed_rad_s), math.degrees(accel_rad_s2)
        if not (math.isfinite(v) and 0.1 <= v <= lim.max_joint_speed_deg_s):
            raise LimitError(ErrorCode.speed_limit, f"joint speed {v:.3g} deg/s is outside [0.1, "
                             f"{lim.max_joint_speed_deg_s}] deg/s")
        if not (math.isfinite(a) and 0 < a <= lim.max_joint_accel_deg_s2):
            raise LimitError(ErrorCode.accel_limit,
                             f"joint acceleration {a:.3g} deg/s^2 is outside (0, "
                             f"{lim.max_joint_accel_deg_s2}] deg/s^2")

    def check_goal(self, T_from: ArrayLike, T_goal: ArrayLike, what: str = "goal",
                   at: ArmAt | None = None) -> None:
        """A straight move from ``T_from`` to ``T_goal``: finite, within the single-move
        distance, and along the whole interpolated path (not only at its ends: orientation
        is interpolated, so tilt can peak in between) within the box and the tilt limit,
        and, given the arm's joints ``at``, within its reach in the configuration it is in."""
        A = np.asarray(T_from, dtype=float)
        B = np.asarray(T_goal, dtype=float)
        if B.shape != (4, 4) or not np.all(np.isfinite(B)):
            raise LimitError(ErrorCode.invalid_pose, f"the {what} pose is not finite")
        dist = float(np.linalg.norm(B[:3, 3] - A[:3, 3]))
        if dist > self.limits.max_move_mm:
            raise LimitError(ErrorCode.move_too_far, f"the {what} is {dist:.1f} mm away (limit "
                             f"{self.limits.max_move_mm} mm for one move)")
        self.check_path(linear_path(A, B), what, at)

    def check_path(self, path: list[NDArray[np.float64]], what: str,
                   at: ArmAt | None = None) -> None:
        """Every pose of a sampled path (first = where the arm is) under the path rule; with
        ``at`` (the arm's joints and TCP), reachable along the way as well."""
        start, goal = path[0], path[-1]
        box0, tilt0 = self.box_violation_mm(start[:3, 3]), self.tilt_excess_deg(start)
        moves = float(np.linalg.norm(goal[:3, 3] - start[:3, 3])) > _EPS
        turns = pose_angle_deg(start, goal) > _EPS
        box_end = self.box_violation_mm(goal[:3, 3])
        tilt_end = self.tilt_excess_deg(goal)
        lo, hi = list(self.limits.workspace_min_mm), list(self.limits.workspace_max_mm)
        if box0 > 0 and moves and box_end >= box0 - _EPS:
            raise LimitError(
                ErrorCode.outside_envelope,
                f"the TCP is {box0:.1f} mm outside the workspace box {lo}..{hi}: only moves "
                f"back towards the box are allowed, and the {what} does not reduce that")
        if tilt0 > 0 and turns and tilt_end >= tilt0 - _EPS:
            raise LimitError(
                ErrorCode.tilt_limit,
                f"the tool is tilted {tilt_deg(start):.1f} deg, past the limit of "
                f"{self.limits.tilt_limit_deg} deg: only rotations back towards vertical are "
                f"allowed, and the {what} does not reduce the tilt")
        for T in path[1:]:
            if self.box_violation_mm(T[:3, 3]) > box0 + _EPS:
                where = "ends" if T is goal else "passes"
                raise LimitError(
                    ErrorCode.outside_envelope,
                    f"the {what} {where} outside the workspace box {lo}..{hi} (at "
                    f"{np.round(T[:3, 3], 1).tolist()} mm)")
            if self.tilt_excess_deg(T) > tilt0 + _EPS:
                where = "at its end" if T is goal else "on its way"
                raise LimitError(
                    ErrorCode.tilt_limit,
                    f"the {what} tilts the tool {tilt_deg(T):.1f} deg from vertical {where} "
                    f"(limit {self.limits.tilt_limit_deg} deg)")
        if at is not None:
            self.reach.check_path(path, what, at)

    def check_jog_speed(self, linear_mm_s: ArrayLike, angular_deg_s: ArrayLike) -> None:
        lin = np.asarray(linear_mm_s, dtype=float)
        ang = np.asarray(angular_deg_s, dtype=float)
        if not (np.all(np.isfinite(lin)) and np.all(np.isfinite(ang))):
            raise LimitError(ErrorCode.invalid_request, "jog speeds must be finite numbers")
        v = float(np.linalg.norm(lin))
        w = float(np.linalg.norm(ang))
        if v > self.limits.max_jog_speed_mm_s:
            raise LimitError(ErrorCode.jog_speed_limit, f"jog speed {v:.1f} mm/s exceeds "
                             f"{self.limits.max_jog_speed_mm_s} mm/s")
        if w > self.limits.max_jog_speed_deg_s:
            raise LimitError(ErrorCode.jog_speed_limit, f"jog rotation speed {w:.1f} deg/s exceeds "
                             f"{self.limits.max_jog_speed_deg_s} deg/s")

    def check_jog_step(self, translation_mm: ArrayLike, rotation_deg: ArrayLike,
                       speed_mm_s: float) -> None:
        """One jog step's size and speed, before any pose is computed."""
        lim = self.limits
        if not (math.isfinite(speed_mm_s)
                and lim.min_speed_mm_s <= speed_mm_s <= lim.max_jog_speed_mm_s):
            raise LimitError(ErrorCode.jog_speed_limit, f"jog speed {speed_mm_s} mm/s is outside "
                             f"[{lim.min_speed_mm_s}, {lim.max_jog_speed_mm_s}] mm/s")
        t = np.asarray(translation_mm, dtype=float).reshape(-1)
        r = np.asarray(rotation_deg, dtype=float).reshape(-1)
        if t.shape != (3,) or r.shape != (3,) or not (np.all(np.isfinite(t))
                                                     and np.all(np.isfinite(r))):
            raise LimitError(ErrorCode.invalid_request,
                             "a jog step needs 3 finite translation_mm and "
                             "3 finite rotation_deg values")
        step_mm, step_deg = float(np.linalg.norm(t)), float(np.linalg.norm(r))
        if step_mm > lim.max_jog_step_mm or step_deg > lim.max_jog_step_deg:
            raise LimitError(
                ErrorCode.jog_step_limit,
                f"a jog step of {step_mm:.1f} mm / {step_deg:.1f} deg is larger than "
                f"limits.max_jog_step_mm = {lim.max_jog_step_mm} / max_jog_step_deg = "
                f"{lim.max_jog_step_deg}: use approach or several steps")

    def check_jog_ahead(self, T_now: ArrayLike, T_ahead: ArrayLike,
                        at: ArmAt | None = None) -> None:
        """A continuous jog continued to ``T_ahead``, under the path rule (LimitError)."""
        self.check_path(linear_path(T_now, T_ahead), "jog", at)


def pose_angle_deg(T_a: ArrayLike, T_b: ArrayLike) -> float:
    A = np.asarray(T_a, dtype=float)[:3, :3]
    B = np.asarray(T_b, dtype=float)[:3, :3]
    c = (np.trace(A.T @ B) - 1.0) / 2.0
    return float(np.degrees(np.arccos(np.clip(c, -1.0, 1.0))))
