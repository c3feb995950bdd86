"""The cell's frame chain: base -> flange -> (tcp, camera) and camera -> target.

Every place that turns an estimate into a robot pose goes through here, so the chain is
written once: ``T_base_target = T_base_tcp(t) @ inv(T_flange_tcp) @ T_flange_camera @
T_camera_target`` where ``t`` is the frame's capture time, or, for a fixed camera,
``T_base_target = T_base_camera @ T_camera_target`` whatever the arm does.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.spatial.transform import Rotation

from cell.error_codes import ErrorCode
from cell.errors import RefusedError
from estimator.transforms import invert_T, make_T, translation_T

if TYPE_CHECKING:
    from cell.config.schema import CellConfig

Matrix4 = NDArray[np.float64]


class FixedCameraError(RefusedError):
    """A flange-camera operation (an observation pose) asked of a fixed camera."""

    def __init__(self, message: str) -> None:
        super().__init__(ErrorCode.not_supported, message)


@dataclass(frozen=True)
class CellFrames:
    """Calibrated mounts: the camera (hand-eye) and the tool centre point on the flange.

    An eye-in-hand camera rides on the flange (``T_flange_camera``); a fixed camera
    (``fixed_T_base_camera`` set, eye-to-hand) stands in the cell, so its pose does not
    depend on the arm's and ``T_flange_camera`` is unused.
    """

    T_flange_camera: Matrix4
    T_flange_tcp: Matrix4
    fixed_T_base_camera: Matrix4 | None = None

    @classmethod
    def fixed(cls, T_base_camera: ArrayLike, T_flange_tcp: ArrayLike) -> CellFrames:
        return cls(np.eye(4), np.asarray(T_flange_tcp, dtype=float),
                   np.asarray(T_base_camera, dtype=float))

    @property
    def is_fixed(self) -> bool:
        return self.fixed_T_base_camera is not None

    @property
    def T_camera_mount(self) -> Matrix4:
        """The calibrated mount: ``T_base_camera`` (fixed) or ``T_flange_camera`` (hand)."""
        if self.fixed_T_base_camera is not None:
            return self.fixed_T_base_camera
        return self.T_flange_camera

    @property
    def T_tcp_camera(self) -> Matrix4:
        if self.fixed_T_base_camera is not None:
            raise FixedCameraError("a fixed camera has no pose on the tool")
        return invert_T(self.T_flange_tcp) @ self.T_flange_camera

    def T_base_camera(self, T_base_tcp: ArrayLike) -> Matrix4:
        if self.fixed_T_base_camera is not None:
            return self.fixed_T_base_camera
        return np.asarray(T_base_tcp, dtype=float) @ self.T_tcp_camera

    def T_base_target(self, T_base_tcp: ArrayLike, T_camera_target: ArrayLike) -> Matrix4:
        return self.T_base_camera(T_base_tcp) @ np.asarray(T_camera_target, dtype=float)

    def T_base_flange(self, T_base_tcp: ArrayLike) -> Matrix4:
        return np.asarray(T_base_tcp, dtype=float) @ invert_T(self.T_flange_tcp)

    def tcp_for_camera(self, T_base_camera: ArrayLike) -> Matrix4:
        """The TCP pose that puts the camera at ``T_base_camera``."""
        return np.asarray(T_base_camera, dtype=float) @ invert_T(self.T_tcp_camera)


def cell_frames(config: CellConfig) -> CellFrames:
    """The frames a config states: the camera on the flange or fixed in the cell."""
    he = config.hand_eye
    if config.fixed_camera and he.T_base_camera is not None:
        return CellFrames.fixed(he.T_base_camera.T(), config.tool.T_flange_tcp.T())
    return CellFrames(he.T_flange_camera.T(), config.tool.T_flange_tcp.T())


def approach_tcp(T_base_target: ArrayLike, T_target_tcp: ArrayLike, standoff_mm: float) -> Matrix4:
    """Approach goal: the TCP ``standoff_mm`` back along its own z from the taught tool pose."""
    return (np.asarray(T_base_target, dtype=float) @ np.asarray(T_target_tcp, dtype=float)
            @ translation_T(0.0, 0.0, -standoff_mm))


def observation_camera(
    T_base_target: ArrayLike, centre_target_mm: ArrayLike, distance_mm: float,
    R_base_camera: ArrayLike | None = None,
) -> Matrix4:
    """Camera pose with the target centre on its optical axis at ``distance_mm``.

    The default orientation looks along the target's +z (head-on, the best-conditioned view);
    a given ``R_base_camera`` keeps that orientation instead (the look-and-move uses the
    approach goal's, so the final move is a pure translation).
    """
    T_bt = np.asarray(T_base_target, dtype=float)
    centre = T_bt[:3, :3] @ np.asarray(centre_target_mm, dtype=float).reshape(3) + T_bt[:3, 3]
    R = T_bt[:3, :3] if R_base_camera is None else np.asarray(R_base_camera, dtype=float)
    return make_T(R, centre - distance_mm * R[:, 2])


def tilt_deg(T_base_tcp: ArrayLike) -> float:
    """Angle between the tool z axis and straight down (base -z), in degrees."""
    z = np.asarray(T_base_tcp, dtype=float)[:3, 2]
    return float(np.degrees(np.arccos(np.clip(-z[2] / np.linalg.norm(z), -1.0, 1.0))))


def mean_pose(Ts: list[Matrix4]) -> Matrix4:
    """Average of nearby poses: mean translation and the chordal mean rotation (SciPy)."""
    R = Rotation.from_matrix(np.stack([T[:3, :3] for T in Ts])).mean().as_matrix()
    return make_T(R, np.mean([T[:3, 3] for T in Ts], axis=0))


def step_goal(T_base_tcp: ArrayLike, translation_mm: ArrayLike, rotation_deg: ArrayLike,
              frame: str) -> Matrix4:
    """Goal of a jog step: a translation and a rotation (rotation vector, deg) about the TCP,
    expressed in the base frame (``frame="base"``) or the tool frame (``"tool"``)."""
    T = np.asarray(T_base_tcp, dtype=float)
    dR = Rotation.from_rotvec(np.radians(np.asarray(rotation_deg, dtype=float))).as_matrix()
    dt = np.asarray(translation_mm, dtype=float).reshape(3)
    if frame == "tool":
        return T @ make_T(dR, dt)
    return make_T(dR @ T[:3, :3], T[:3, 3] + dt)
