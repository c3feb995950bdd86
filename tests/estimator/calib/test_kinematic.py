"""The hand-eye transform fitted with the arm's geometry, on views of an arm whose true DH
table is off the published one by the amounts an uncalibrated UR is (tenths of a mm and of a
mrad per joint): the joint refinement absorbs the arm's error into the mount, the kinematic fit
does not."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from estimator import CameraModel
from estimator.calib.handeye import HandEyeError, refine_joint
from estimator.calib.kinematic import MIN_VIEWS, refine_kinematic
from estimator.kinematics import UR_DH, forward
from estimator.transforms import invert_T, make_T, pose_distance

NOMINAL = UR_DH["ur5e"]
TRUE = NOMINAL.perturbed((0.0, 3e-4, -2.5e-4, 2.5e-4, -3e-4, 0.0),
                         (0.25, 0.0, 0.0, -0.2, 0.15, 0.0), (0.0, 0.3, -0.3, 0.0, 0.0, 0.0))
CAMERA = CameraModel(806.4, 805.6, 643.0, 397.0, (-0.045, 0.012, 0.0004, -0.0003, 0.0),
                     1280, 800)
T_FLANGE_CAMERA = make_T(Rotation.from_rotvec([0.004, -0.003, 0.006]).as_matrix(),
                         [1.2, 58.2, 31.5])
Q_HOME = np.radians([0.0, -90.0, 90.0, -90.0, -90.0, 0.0])
DOTS_MM = np.array([[x, y, 0.0] for x in (-50.0, 0.0, 50.0) for y in (-35.0, 0.0, 35.0)])


def _views(n: int, seed: int = 3) -> tuple[list[np.ndarray], list[np.ndarray], np.ndarray]:
    """Joint sets that turn the wrist and the elbow around home, the dots seen from each
    (0.01 px of noise), and the plate's true base pose (450 mm ahead of the camera at home)."""
    rng = np.random.default_rng(seed)
    T_base_board = forward(TRUE, Q_HOME) @ T_FLANGE_CAMERA @ make_T(np.eye(3), [0, 0, 450.0])
    joints, points = [], []
    for _ in range(n):
        q = Q_HOME + np.radians(rng.uniform(-1, 1, 6) * (8, 8, 10, 20, 20, 40))
        C = invert_T(forward(TRUE, q) @ T_FLANGE_CAMERA) @ T_base_board
        pc = (C[:3, :3] @ DOTS_MM.T).T + C[:3, 3]
        joints.append(q)
        points.append(CAMERA.project(pc) + rng.normal(0.0, 0.01, (len(DOTS_MM), 2)))
    return joints, points, T_base_board


def test_the_arms_geometry_is_fitted_and_the_mount_is_not_bent_by_it() -> None:
    joints, points, T_base_board = _views(24)
    flanges = [forward(NOMINAL, q) for q in joints]  # what the arm reports
    guess = make_T(np.eye(3), [0.0, 60.0, 30.0])
    joint = refine_joint(flanges, points, DOTS_MM, CAMERA, guess,
                         flanges[0] @ guess @ make_T(np.eye(3), [0, 0, 450.0]))
    kin = refine_kinematic(joints, points, [DOTS_MM] * len(points), CAMERA, NOMINAL,
                           joint.T_flange_camera, joint.T_base_board)
    joint_mm, joint_deg = pose_distance(joint.T_flange_camera, T_FLANGE_CAMERA)
    kin_mm, kin_deg = pose_distance(kin.T_flange_camera, T_FLANGE_CAMERA)
    assert kin.converged and kin.rms_px < 0.03 and joint.rms_px > 4 * kin.rms_px, (
        kin.rms_px, joint.rms_px)
    assert kin_mm < 0.05 and kin_deg < 0.01, (kin_mm, kin_deg)
    assert joint_mm > 2 * kin_mm or joint_deg > 2 * kin_deg, (joint_mm, joint_deg)
    # the fitted table predicts where the plate is seen from poses the fit did not see
    fitted = kin.table(NOMINAL)
    for q in _views(5, seed=11)[0]:
        seen = invert_T(forward(TRUE, q) @ T_FLANGE_CAMERA) @ T_base_board
        predicted = invert_T(forward(fitted, q) @ kin.T_flange_camera) @ kin.T_base_board
        assert pose_distance(predicted, seen)[0] < 0.05


def test_too_few_views_or_mismatched_inputs_are_refused() -> None:
    joints, points, T_base_board = _views(MIN_VIEWS - 1)
    with pytest.raises(HandEyeError, match="at least"):
        refine_kinematic(joints, points, [DOTS_MM] * len(points), CAMERA, NOMINAL,
                         T_FLANGE_CAMERA, T_base_board)
    joints, points, T_base_board = _views(MIN_VIEWS)
    with pytest.raises(HandEyeError, match="joint sets"):
        refine_kinematic(joints[:-1], points, [DOTS_MM] * len(points), CAMERA, NOMINAL,
                         T_FLANGE_CAMERA, T_base_board)
