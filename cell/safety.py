"""Typed refusals and the checks that produce them, run BEFORE anything is commanded.

Every refusal is a :class:`CellError` with a machine-readable ``code``, a ``kind`` the API
maps to an HTTP status, and a message that tells a person what to do. Checks only read; a
failed check therefore guarantees that nothing moved.
"""

from __future__ import annotations

from typing import ClassVar, Literal

import numpy as np
from numpy.typing import ArrayLike

from cell.config import LimitsConfig
from cell.frames import tilt_deg
from drivers.arm import ArmState

ErrorKind = Literal["invalid", "conflict", "unavailable", "not_found", "unauthorized",
                    "forbidden"]


class CellError(Exception):
    """Base of every refusal or failure the cell reports to its callers."""

    kind: ClassVar[ErrorKind] = "conflict"

    def __init__(self, code: str, message: str) -> None:
        super().__init__(message)
        self.code = code
        self.message = message


class LimitError(CellError):
    """The request itself breaks a configured limit (envelope, speed, tilt, distance)."""

    kind = "invalid"


class RefusedError(CellError):
    """The request is fine but the cell's state forbids it now (busy, stopped, stale pose)."""

    kind = "conflict"


class UnavailableError(CellError):
    """A device the request needs is not available (camera lost, arm disconnected)."""

    kind = "unavailable"


class NotFoundError(CellError):
    kind = "not_found"


class SafetyGuard:
    """The configured limits as checks; stateless apart from the limits."""

    def __init__(self, limits: LimitsConfig) -> None:
        self.limits = limits
        self._lo = np.asarray(limits.workspace_min_mm, dtype=float)
        self._hi = np.asarray(limits.workspace_max_mm, dtype=float)

    def in_envelope(self, position_mm: ArrayLike) -> bool:
        p = np.asarray(position_mm, dtype=float).reshape(3)
        return bool(np.all(p >= self._lo) and np.all(p <= self._hi))

    def check_arm(self, state: ArmState, now_s: float) -> None:
        """The arm can take a motion command now, and its state is fresh."""
        if not state.connected:
            raise UnavailableError("arm_disconnected",
                                   "the arm is not connected; check the controller and network")
        if state.emergency_stop:
            raise RefusedError("emergency_stop",
                               "the arm is emergency-stopped; release the e-stop at the cell")
        if state.protective_stop:
            raise RefusedError("protective_stop",
                               "the arm is protective-stopped; clear the cause and unlock it "
                               "on the pendant before moving")
        if not state.ready:
            raise RefusedError("arm_not_ready",
                               f"the arm is not ready for motion (mode {state.robot_mode}, "
                               f"safety {state.safety_status})")
        age = now_s - state.timestamp_s
        if age > self.limits.max_pose_age_s:
            raise RefusedError("stale_pose",
                               f"the arm's pose is {age:.2f} s old (limit "
                               f"{self.limits.max_pose_age_s} s); the robot state stream stalled")

    def check_speed(self, speed_mm_s: float, accel_mm_s2: float) -> None:
        if not 0 < speed_mm_s <= self.limits.max_speed_mm_s:
            raise LimitError("speed_limit", f"speed {speed_mm_s} mm/s is outside (0, "
                             f"{self.limits.max_speed_mm_s}] mm/s")
        if not 0 < accel_mm_s2 <= self.limits.max_accel_mm_s2:
            raise LimitError("accel_limit", f"acceleration {accel_mm_s2} mm/s^2 is outside (0, "
                             f"{self.limits.max_accel_mm_s2}] mm/s^2")

    def check_goal(self, T_from: ArrayLike, T_goal: ArrayLike, what: str = "goal") -> None:
        """A straight move from ``T_from`` to ``T_goal`` stays in the box (both ends of a line in
        a convex box bound the whole line), within the tilt limit and the single-move distance."""
        A = np.asarray(T_from, dtype=float)
        B = np.asarray(T_goal, dtype=float)
        if not np.all(np.isfinite(B)):
            raise LimitError("invalid_pose", f"the {what} pose is not finite")
        p = B[:3, 3]
        if not self.in_envelope(p):
            raise LimitError(
                "outside_envelope",
                f"the {what} TCP position {np.round(p, 1).tolist()} mm is outside the workspace "
                f"box {list(self.limits.workspace_min_mm)}..{list(self.limits.workspace_max_mm)}")
        tilt = tilt_deg(B)
        if tilt > self.limits.tilt_limit_deg:
            raise LimitError("tilt_limit", f"the {what} pose tilts the tool {tilt:.1f} deg from "
                             f"vertical (limit {self.limits.tilt_limit_deg} deg)")
        dist = float(np.linalg.norm(p - A[:3, 3]))
        if dist > self.limits.max_move_mm:
            raise LimitError("move_too_far", f"the {what} is {dist:.1f} mm away (limit "
                             f"{self.limits.max_move_mm} mm for one move)")

    def check_jog_speed(self, linear_mm_s: ArrayLike, angular_deg_s: ArrayLike) -> None:
        v = float(np.linalg.norm(np.asarray(linear_mm_s, dtype=float)))
        w = float(np.linalg.norm(np.asarray(angular_deg_s, dtype=float)))
        if v > self.limits.max_jog_speed_mm_s:
            raise LimitError("jog_speed_limit", f"jog speed {v:.1f} mm/s exceeds "
                             f"{self.limits.max_jog_speed_mm_s} mm/s")
        if w > self.limits.max_jog_speed_deg_s:
            raise LimitError("jog_speed_limit", f"jog rotation speed {w:.1f} deg/s exceeds "
                             f"{self.limits.max_jog_speed_deg_s} deg/s")

    def jog_allowed(self, T_now: ArrayLike, T_ahead: ArrayLike) -> bool:
        """False when the jog, continued to ``T_ahead``, would leave the box or pass the tilt
        limit. Moving back towards the allowed region is always possible, so an operator can
        recover a TCP that is already outside."""
        A = np.asarray(T_now, dtype=float)
        B = np.asarray(T_ahead, dtype=float)
        if self.in_envelope(A[:3, 3]) and not self.in_envelope(B[:3, 3]):
            return False
        tilt_ahead = tilt_deg(B)
        return not (tilt_ahead > self.limits.tilt_limit_deg and tilt_ahead > tilt_deg(A))
