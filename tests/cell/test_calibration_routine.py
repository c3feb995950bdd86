"""The hand-eye routine's loop on stand-ins for the arm and the camera (no simulator): which
refusals skip a view and which end the routine."""

from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Any

import cv2
import numpy as np
import pytest
from numpy.typing import NDArray

from cell.calibration.observe import Observation
from cell.calibration.routine import RoutineSettings, run_hand_eye_routine
from cell.calibration.solve import solve_observations
from cell.error_codes import ErrorCode
from cell.errors import RefusedError
from drivers.camera import Frame
from estimator import CameraModel
from estimator.kinematics import forward
from estimator.transforms import T_from_pose, invert_T, make_T, pose_distance
from tests.estimator.calib.test_kinematic import CAMERA as KIN_CAMERA
from tests.estimator.calib.test_kinematic import DOTS_MM, NOMINAL, T_FLANGE_CAMERA
from tests.estimator.calib.test_kinematic import _views as kinematic_views

CAMERA = CameraModel(800.0, 800.0, 639.5, 399.5, (), 1280, 800)
X = T_from_pose([0.0, 60.0, 30.0], [0.0, 0.0, 0.0])
W = T_from_pose([-480.0, -100.0, 0.0], [np.pi, 0.0, 0.0])
DOTS = np.array([[0, 0, 0], [60, 0, 0], [100, 10, 0], [0, 50, 0], [40, 70, 0], [90, 60, 0.0]])


@dataclass
class _State:
    ready: bool = True


class StubArm:
    """Moves instantly; the ``refuse_at``-th move is refused with ``code``."""

    def __init__(self, refuse_at: int, code: ErrorCode) -> None:
        self.T = W @ T_from_pose([50.0, 35.0, -456.0], [0.0, 0.0, 0.0]) @ invert_T(X)
        self.moves, self.refuse_at, self.code = 0, refuse_at, code

    def tcp_pose(self) -> NDArray[np.float64]:
        return self.T

    def pose_at(self, t_s: float) -> NDArray[np.float64]:
        return self.T

    def state(self) -> _State:
        return _State()

    def joint_positions_rad(self) -> NDArray[np.float64]:
        return np.zeros(6)

    def move_linear(self, T: NDArray[np.float64], speed: float, accel: float) -> None:
        self.moves += 1
        if self.moves == self.refuse_at:
            raise RefusedError(self.code, "moving to the move: out of reach")
        self.T = np.asarray(T, dtype=float)


class StubCamera:
    def latest_frame(self, timeout_s: float) -> Frame:
        return Frame(np.zeros((800, 1280), np.uint8), time.monotonic() + 1.0, 0, CAMERA)


def _observer(arm: StubArm) -> Any:
    def observe(image: NDArray[np.uint8], camera: CameraModel) -> Observation:
        T_cb = invert_T(arm.T @ X) @ W
        pts = (T_cb[:3, :3] @ DOTS.T).T + T_cb[:3, 3]
        return Observation(DOTS, camera.project(pts), T_cb, 0.0)
    return observe


def test_an_unreachable_view_is_skipped_and_other_refusals_end_the_routine() -> None:
    settings = RoutineSettings(n_views=8, settle_s=0.0)
    arm = StubArm(3, ErrorCode.motion_failed)  # the controller: out of reach
    result = run_hand_eye_routine(arm, StubCamera(), _observer(arm), np.eye(4), X,  # type: ignore[arg-type]
                                  settings)
    assert [k for k, _ in result.failed] == [3] and len(result.observations) == 7
    assert "out of reach" in result.failed[0][1]
    busy = StubArm(3, ErrorCode.busy)
    with pytest.raises(RefusedError):
        run_hand_eye_routine(busy, StubCamera(), _observer(busy), np.eye(4), X,  # type: ignore[arg-type]
                             settings)



def _plate_pose(points_px: NDArray[np.float64]) -> NDArray[np.float64]:
    """The plate's pose in the camera from one view's dots (what the observer reports)."""
    ok, rvec, tvec = cv2.solvePnP(DOTS_MM, points_px, KIN_CAMERA.K, KIN_CAMERA.dist_coeffs)
    assert ok
    return make_T(cv2.Rodrigues(rvec)[0], tvec.ravel())


def test_auto_takes_the_kinematic_fit_when_the_arms_geometry_explains_the_views() -> None:
    """Views of an arm off its nominal DH table (tests/estimator/calib/test_kinematic.py): with
    their joints the solver chooses the kinematic fit, the verdict is consistent and the chosen
    mount is the true one; without joints it falls back to the hybrid."""
    joints, points, _ = kinematic_views(24)
    flanges = [forward(NOMINAL, q) for q in joints]  # what the arm reports
    names = [f"view-{k:02d}" for k in range(len(joints))]
    args = (KIN_CAMERA, names, flanges, [DOTS_MM] * len(joints), points,
            [_plate_pose(p) for p in points], [0.01] * len(joints))
    with_joints = solve_observations(*args, joints_rad=joints, arm_geometry=NOMINAL)
    assert with_joints.chosen == "kinematic" and with_joints.verdict.consistent, (
        with_joints.verdict.text)
    assert "nominal kinematics" in with_joints.verdict.text
    d_mm, d_deg = pose_distance(with_joints.T_flange_camera, T_FLANGE_CAMERA)
    assert d_mm < 0.05 and d_deg < 0.01, (d_mm, d_deg)
    kinematic = with_joints.solution().kinematic
    assert kinematic is not None and kinematic.rms_px < 0.03
    without = solve_observations(*args)
    assert without.chosen == "hybrid" and without.kinematic is None
