"""Where the camera is in the IBVS loop: on the flange (eye-in-hand) or fixed in the cell
(eye-to-hand, watching a dot plate clamped to the tool).

The law (:mod:`cell.servoing.image`) is the same for both; what differs is the geometry, kept
here in one place:

- the law's twist: the camera's (eye-in-hand) or the plate's, opposite in sign
  (:func:`cell.servoing.ibvs.carried_twist`), both in the camera frame about its origin, and
  mapped to the TCP's base-frame twist the same way (the camera's pose in the base frame, the
  lever to the TCP): with the hand camera through the hand-eye transform, with the fixed one
  through ``[hand_eye] T_base_camera``. An error in either only bends the path;
- the motion of the dots in the camera frame since a frame's exposure (for the prediction): the
  camera's motion (hand), or the tool's seen from the still camera (fixed);
- the TCP in the camera frame (for the remaining motion the view asks for);
- the pose-based goal a view implies (checked against the envelope, reported as the estimated
  error): the target's pose and the taught ``T_target_tcp`` (hand), or the TCP moved by what
  takes the plate from where it is now to where the taught view had it (fixed);
- the settle's straight step.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from cell.servoing.ibvs import (
    Features,
    InteractionFrom,
    base_tcp_twist,
    camera_twist,
    carried_twist,
    view_pose,
)
from cell.servoing.ibvs_settle import step_goal
from cell.vision.frames import CellFrames
from estimator.transforms import T_from_pose, invert_T

Matrix4 = NDArray[np.float64]
Vec = NDArray[np.float64]


@dataclass(frozen=True)
class IbvsMount:
    """The camera's mount as the IBVS loop sees it. ``T_camera_taught``: the taught view's
    pose of the plate in the fixed camera (None for a camera on the flange)."""

    fixed: bool
    T_tcp_camera: Matrix4 | None  # hand
    T_base_camera: Matrix4 | None  # fixed
    T_camera_taught: Matrix4 | None  # fixed

    @classmethod
    def of(cls, frames: CellFrames, desired: Features, target_points_mm: NDArray[np.float64]
           ) -> IbvsMount:
        if frames.is_fixed:
            return cls(True, None, frames.T_camera_mount, view_pose(desired, target_points_mm))
        return cls(False, frames.T_tcp_camera, None, None)

    def camera(self, T_base_tcp: Matrix4) -> Matrix4:
        """``T_base_camera`` with the arm at ``T_base_tcp``."""
        if self.T_base_camera is not None:
            return self.T_base_camera
        assert self.T_tcp_camera is not None
        return np.asarray(T_base_tcp @ self.T_tcp_camera, dtype=float)

    def tcp_twist(self, current: Features, desired: Features, gain: Callable[[float], float],
                  interaction: InteractionFrom, T_base_tcp: Matrix4) -> Vec:
        """The law's step as the TCP's base-frame twist (mm/s, rad/s)."""
        v = (carried_twist if self.fixed else camera_twist)(current, desired, gain, interaction)
        return base_tcp_twist(v, self.camera(T_base_tcp), T_base_tcp)

    def dots_motion(self, T_base_tcp_now: Matrix4, T_base_tcp_then: Matrix4) -> Matrix4:
        """How the dots moved in the camera frame between two arm poses (camera frame then to
        camera frame now): the camera's own motion, or the tool's seen from the still camera."""
        if self.fixed:
            T_bc = self.camera(T_base_tcp_now)
            return np.asarray(invert_T(T_bc) @ T_base_tcp_now @ invert_T(T_base_tcp_then)
                              @ T_bc, dtype=float)
        return np.asarray(invert_T(self.camera(T_base_tcp_now)) @ self.camera(T_base_tcp_then),
                          dtype=float)

    def camera_tcp(self, T_base_tcp: Matrix4) -> Matrix4:
        """The TCP in the camera frame."""
        return np.asarray(invert_T(self.camera(T_base_tcp)) @ T_base_tcp, dtype=float)

    def goal(self, T_base_target: Matrix4, T_base_tcp: Matrix4, T_target_tcp: Matrix4
             ) -> Matrix4:
        """The TCP pose a view implies, from its pose estimate (the target's, or the tool
        plate's, in the base frame) and the arm pose at its exposure."""
        if self.fixed:
            assert self.T_camera_taught is not None
            T_plate_tcp = invert_T(T_base_target) @ T_base_tcp
            return np.asarray(self.camera(T_base_tcp) @ self.T_camera_taught @ T_plate_tcp,
                              dtype=float)
        return np.asarray(T_base_target @ T_target_tcp, dtype=float)

    def step_goal(self, T_base_tcp: Matrix4, step: Vec) -> Matrix4:
        """The TCP pose after the settle's step ``[dp mm, dtheta rad]``: the camera's motion
        relative to the dots, in the camera frame (the camera moves by it; a fixed camera's
        plate moves by its inverse)."""
        if not self.fixed:
            assert self.T_tcp_camera is not None
            return step_goal(T_base_tcp, self.T_tcp_camera, step)
        T_bc = self.camera(T_base_tcp)
        return np.asarray(T_bc @ invert_T(T_from_pose(step[:3], step[3:])) @ invert_T(T_bc)
                          @ T_base_tcp, dtype=float)
