"""Hand-eye solvers, the joint refinement and the verdict: synthetic truth and ViSP's real views."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from numpy.typing import NDArray
from scipy.spatial.transform import Rotation

from cell.calibration.dataset import load_dataset
from cell.calibration.report import HandEyeReport
from cell.calibration.solve import solve_dataset, solve_views
from estimator import CameraModel
from estimator.calib.board import Board, board_pose, chessboard, detect_board
from estimator.calib.handeye import (
    SOLVERS,
    HandEyeError,
    board_spread,
    refine_joint,
    solve_hand_eye,
)
from estimator.transforms import T_from_pose, invert_T, make_T, pose_distance

# ViSP's published eMc and rMo for the data-eye-in-hand set (SOURCE.md).
VISP_T_FLANGE_CAMERA = T_from_pose(
    np.array([0.05771519632, -0.03392488515, -0.04227690244]) * 1000.0,
    [0.001783530191, 0.009173747947, 1.581782359],
)
VISP_T_BASE_BOARD = T_from_pose(
    np.array([0.5364858483, 0.123945742, 0.09155742609]) * 1000.0,
    [2.22636085, -2.213916548, 0.02071766945],
)
VISP_RESIDUAL_MM, VISP_RESIDUAL_DEG = 5.41, 0.456

CAMERA = CameraModel(800.0, 802.0, 640.5, 399.0, (), 1280, 800)
BOARD = chessboard(9, 6, 25.0)
TRUE_X = T_from_pose([42.0, -61.0, 35.5], [0.05, -0.12, 1.55])
TRUE_W = T_from_pose([520.0, 80.0, 15.0], [np.pi, 0.0, 0.3])


def synthetic_views(
    n: int, seed: int, noise_px: float = 0.0
) -> tuple[list[NDArray[np.float64]], list[NDArray[np.float64]]]:
    """Robot poses looking down at the board from ~450 mm, tilted up to ~30 deg; projections."""
    rng = np.random.default_rng(seed)
    centre_base = TRUE_W[:3, :3] @ BOARD.object_points_mm().mean(axis=0) + TRUE_W[:3, 3]
    flanges: list[NDArray[np.float64]] = []
    points: list[NDArray[np.float64]] = []
    while len(flanges) < n:
        tilt = Rotation.from_rotvec(np.r_[rng.uniform(-0.5, 0.5, 2), rng.uniform(-1.0, 1.0)])
        R_base_camera = (Rotation.from_rotvec([np.pi, 0, 0]) * tilt).as_matrix()
        cam_pos = centre_base - R_base_camera[:, 2] * rng.uniform(380, 520)
        T_base_camera = make_T(R_base_camera, cam_pos + rng.normal(0, 20, 3))
        T_base_flange = T_base_camera @ invert_T(TRUE_X)
        T_camera_board = invert_T(T_base_camera) @ TRUE_W
        pts_cam = (T_camera_board[:3, :3] @ BOARD.object_points_mm().T).T + T_camera_board[:3, 3]
        uv = CAMERA.project(pts_cam) + rng.normal(0, noise_px, (BOARD.n_points, 2))
        if np.all((uv > 0) & (uv < [CAMERA.width, CAMERA.height])):
            flanges.append(T_base_flange)
            points.append(uv)
    return flanges, points


def board_poses(points: list[NDArray[np.float64]]) -> list[NDArray[np.float64]]:
    return [board_pose(BOARD, p, CAMERA).T_camera_board for p in points]


@pytest.mark.parametrize("method", sorted(SOLVERS))
def test_every_method_recovers_exact_hand_eye(method: str) -> None:
    flanges, points = synthetic_views(10, seed=1)
    X = solve_hand_eye(method, flanges, board_poses(points))
    d_mm, d_deg = pose_distance(X, TRUE_X)
    assert d_mm < 1e-6 and np.radians(d_deg) < 1e-6
    spread = board_spread(flanges, board_poses(points), X)
    assert spread.mean_mm < 1e-6 and spread.mean_deg < 1e-6
    assert pose_distance(spread.T_base_board_mean, TRUE_W)[0] < 1e-6


def test_joint_refinement_recovers_truth_from_a_poor_start() -> None:
    flanges, points = synthetic_views(8, seed=2)
    start_X = TRUE_X @ T_from_pose([4.0, -3.0, 5.0], [0.02, -0.03, 0.01])
    start_W = TRUE_W @ T_from_pose([-6.0, 5.0, 2.0], [0.01, 0.02, -0.02])
    joint = refine_joint(flanges, points, BOARD.object_points_mm(), CAMERA, start_X, start_W)
    d_mm, d_deg = pose_distance(joint.T_flange_camera, TRUE_X)
    assert d_mm < 1e-6 and np.radians(d_deg) < 1e-6
    assert pose_distance(joint.T_base_board, TRUE_W)[0] < 1e-6
    assert joint.rms_px < 1e-6 and joint.converged


def test_hybrid_holds_the_rotation_and_refines_the_rest() -> None:
    flanges, points = synthetic_views(8, seed=2)
    start_X = make_T(TRUE_X[:3, :3], TRUE_X[:3, 3] + [4.0, -3.0, 5.0])
    start_W = TRUE_W @ T_from_pose([-6.0, 5.0, 2.0], [0.01, 0.02, -0.02])
    held = refine_joint(flanges, points, BOARD.object_points_mm(), CAMERA, start_X, start_W,
                        hold_rotation=True)
    assert np.array_equal(held.T_flange_camera[:3, :3], TRUE_X[:3, :3])
    assert pose_distance(held.T_flange_camera, TRUE_X)[0] < 1e-6 and held.rms_px < 1e-6
    assert pose_distance(held.T_base_board, TRUE_W)[0] < 1e-6
    assert np.all(held.std_rotvec_deg == 0.0)


def test_noisy_views_stay_accurate_and_are_judged_consistent() -> None:
    flanges, points = synthetic_views(12, seed=3, noise_px=0.2)
    names = [f"v{i}" for i in range(len(flanges))]
    report = solve_views(CAMERA, BOARD, names, flanges, points, chosen="park")
    for m in report.methods.values():
        d_mm, d_deg = pose_distance(m.T_flange_camera, TRUE_X)
        assert d_mm < 1.5 and d_deg < 0.1, (m.method, d_mm, d_deg)
    assert report.joint is not None
    d_mm, d_deg = pose_distance(report.joint.T_flange_camera, TRUE_X)
    assert d_mm < 0.5 and d_deg < 0.05
    assert report.joint.rms_px == pytest.approx(0.2 * np.sqrt(2), rel=0.3)
    assert report.verdict.consistent, report.verdict.text
    # the default (auto) takes the joint fit: it leaves no more than the images' own noise
    default = solve_views(CAMERA, BOARD, names, flanges, points)
    assert default.chosen == "joint" and default.verdict.consistent


def test_auto_takes_the_motions_rotation_when_the_poses_are_slightly_off() -> None:
    """Flange poses a few tenths of a millimetre off (an arm on its nominal kinematics): the
    free joint fit leaves far more than the images' noise; auto chooses the hybrid, which
    keeps the AX = XB rotation and fits the translation to every image point."""
    flanges, points = synthetic_views(12, seed=3, noise_px=0.05)
    rng = np.random.default_rng(11)
    bent = [T @ T_from_pose(rng.normal(0, 0.15, 3), rng.normal(0, 1.5e-4, 3)) for T in flanges]
    report = solve_views(CAMERA, BOARD, [f"v{i}" for i in range(12)], bent, points)
    assert report.chosen == "hybrid" and report.hybrid is not None and report.joint is not None
    assert report.joint.rms_px > 4.0 * float(np.median(report.pnp_rms_px))
    assert np.allclose(report.T_flange_camera[:3, :3],
                       report.methods["park"].T_flange_camera[:3, :3], atol=1e-12)
    d_mm, d_deg = pose_distance(report.T_flange_camera, TRUE_X)
    j_mm, j_deg = pose_distance(report.joint.T_flange_camera, TRUE_X)
    assert d_deg < 0.03 and d_deg < j_deg / 5 and d_mm < j_mm, (d_mm, d_deg, j_mm, j_deg)
    assert report.verdict.consistent, report.verdict.text
    assert "rotation is taken from the motions" in report.verdict.text


def test_inconsistent_robot_poses_are_called_out() -> None:
    """Millimetre errors in the reported flange poses: images alone fit, together they do not."""
    flanges, points = synthetic_views(10, seed=4, noise_px=0.1)
    rng = np.random.default_rng(7)
    bent = [T @ T_from_pose(rng.normal(0, 3.0, 3), rng.normal(0, 0.004, 3)) for T in flanges]
    report = solve_views(CAMERA, BOARD, [str(i) for i in range(10)], bent, points)
    assert not report.verdict.consistent
    assert report.joint is not None and report.joint.rms_px > 2.0
    assert "robot" in report.verdict.text
    assert "intrinsics are not the main cause" in report.verdict.text


def test_wrong_intrinsics_are_blamed() -> None:
    flanges, points = synthetic_views(10, seed=5, noise_px=0.1)
    wrong = CameraModel(CAMERA.fx * 1.06, CAMERA.fy * 1.06, CAMERA.cx + 25, CAMERA.cy - 20, (),
                        CAMERA.width, CAMERA.height)
    report = solve_views(wrong, BOARD, [str(i) for i in range(10)], flanges, points)
    assert not report.verdict.consistent
    assert "intrinsics are the likely cause" in report.verdict.text


def test_degenerate_motions_are_refused() -> None:
    flanges, points = synthetic_views(6, seed=6)
    poses = board_poses(points)
    with pytest.raises(HandEyeError, match="at least 3 views"):
        solve_hand_eye("tsai", flanges[:2], poses[:2])
    # pure translations: no rotation axis at all
    shifted = [flanges[0] @ T_from_pose([10.0 * k, 0, 0], [0, 0, 0]) for k in range(4)]
    same = [invert_T(T @ TRUE_X) @ TRUE_W for T in shifted]
    with pytest.raises(HandEyeError, match="two different axes"):
        solve_hand_eye("park", shifted, same)
    with pytest.raises(HandEyeError, match="unknown"):
        solve_hand_eye("magic", flanges, poses)


# --- ViSP's real eye-in-hand views --------------------------------------------------------


@pytest.fixture(scope="module")
def visp_report(visp_dir: Path) -> HandEyeReport:
    return solve_dataset(load_dataset(visp_dir))


@pytest.mark.parametrize("method", sorted(SOLVERS))
def test_real_data_reproduces_visp(visp_report: HandEyeReport, method: str) -> None:
    m = visp_report.methods[method]
    d_mm, d_deg = pose_distance(m.T_flange_camera, VISP_T_FLANGE_CAMERA)
    assert d_mm < 1.0 and d_deg < 0.1, (method, d_mm, d_deg)
    assert m.spread.mean_mm <= VISP_RESIDUAL_MM and m.spread.mean_deg <= VISP_RESIDUAL_DEG
    # same board frame as ViSP's (canonical corner order): rMo agrees too
    w_mm, w_deg = pose_distance(m.spread.T_base_board_mean, VISP_T_BASE_BOARD)
    assert w_mm < 2.0 and w_deg < 0.2


def test_real_data_verdict_explains_the_pixel_rms(visp_report: HandEyeReport) -> None:
    assert len(visp_report.view_names) == 8 and not visp_report.skipped_views
    assert max(visp_report.pnp_rms_px) < 1.0  # each image fits its own board pose
    assert visp_report.joint is not None and 2.0 < visp_report.joint.rms_px < 10.0
    assert not visp_report.verdict.consistent
    text = visp_report.verdict.text
    hybrid = visp_report.hybrid
    assert hybrid is not None and hybrid.rms_px > 2.0
    assert f"{hybrid.rms_px:.2f} px" in text and "robot" in text
    # the default (as the routine's) is the hybrid: the motions' rotation, the translation
    # from every image point, which no single mount fits on these data (the verdict says so)
    assert visp_report.chosen == "hybrid"
    assert np.allclose(visp_report.T_flange_camera, hybrid.T_flange_camera)
    # the free joint fit moves millimetres away from the AX = XB answers
    assert pose_distance(visp_report.joint.T_flange_camera,
                         visp_report.methods["tsai"].T_flange_camera)[0] > 2.0
    assert pose_distance(visp_report.methods["tsai"].T_flange_camera, VISP_T_FLANGE_CAMERA)[0] < 1.0


def test_detection_order_is_canonical_under_180_degree_turns(visp_dir: Path) -> None:
    import cv2

    board = Board("chessboard", 9, 6, 23.6)
    loaded = cv2.imread(str(visp_dir / "franka_image-1.png"), cv2.IMREAD_GRAYSCALE)
    assert loaded is not None
    img = np.asarray(loaded, dtype=np.uint8)
    a = detect_board(board, img)
    b = detect_board(board, np.ascontiguousarray(img[::-1, ::-1]))
    assert a is not None and b is not None
    h, w = img.shape
    b_back = np.column_stack((w - 1 - b[:, 0], h - 1 - b[:, 1]))
    assert np.max(np.linalg.norm(a - b_back, axis=1)) < 0.5


def test_planned_routine_poses_turn_about_the_target() -> None:
    from cell.calibration.routine import RoutineSettings, plan_poses

    start = T_from_pose([-400.0, -100.0, 450.0], [np.pi, 0.0, 0.0])
    pivot_cam = np.array([10.0, -20.0, 400.0])
    settings = RoutineSettings(n_views=10, tilt_deg=20.0, roll_deg=30.0)
    poses = plan_poses(start, TRUE_X, pivot_cam, settings)
    assert len(poses) == 10 and np.allclose(poses[0], start)
    pivot_base = start @ TRUE_X @ np.r_[pivot_cam, 1.0]
    axes = []
    for T in poses[1:]:
        in_cam = invert_T(T @ TRUE_X) @ pivot_base
        assert np.linalg.norm(in_cam[:3]) == pytest.approx(np.linalg.norm(pivot_cam), abs=1e-6)
        turn = invert_T(start) @ T
        axes.append(Rotation.from_matrix(turn[:3, :3]).as_rotvec())
    assert np.linalg.matrix_rank(np.array(axes), tol=0.05) == 3  # many different axes
    angles = np.degrees(np.linalg.norm(axes, axis=1))
    assert angles.max() < 20.0 + 30.0 + 1.0
