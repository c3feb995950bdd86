"""Intrinsics from rendered board images with a known camera, and board detection order."""

from __future__ import annotations

import numpy as np
import pytest
from numpy.typing import NDArray
from scipy.spatial.transform import Rotation

from estimator import CameraModel
from estimator.calib.board import Board, board_pose, chessboard, detect_board
from estimator.calib.intrinsics import IntrinsicsError, calibrate_intrinsics
from estimator.calib.synthetic import render_board
from estimator.transforms import make_T, pose_distance

TRUE = CameraModel(812.0, 806.0, 652.0, 388.0, (), 1280, 800)


def board_views(board: Board, n: int, seed: int) -> list[NDArray[np.float64]]:
    """Board poses 450-750 mm away, tilted up to ~30 deg, centred near the optical axis."""
    rng = np.random.default_rng(seed)
    centre = board.object_points_mm().mean(axis=0)
    poses = []
    for _ in range(n):
        R = Rotation.from_rotvec(np.r_[rng.uniform(-0.5, 0.5, 2), rng.uniform(-0.4, 0.4)])
        t = np.r_[rng.uniform(-80, 80, 2), rng.uniform(450, 750)]
        poses.append(make_T(R.as_matrix(), t - R.as_matrix() @ centre))
    return poses


@pytest.mark.parametrize(
    "board", [chessboard(9, 6, 25.0), Board("circles", 7, 5, 30.0), Board("acircles", 4, 11, 40.0)],
    ids=lambda b: b.kind,
)
def test_recovers_focal_lengths_and_principal_point(board: Board) -> None:
    images = [render_board(board, TRUE, T, noise_sigma=2.0, seed=k)
              for k, T in enumerate(board_views(board, 10, seed=11))]
    result = calibrate_intrinsics(board, images, distortion=False)
    cam = result.camera
    assert cam.fx == pytest.approx(TRUE.fx, rel=0.01)
    assert cam.fy == pytest.approx(TRUE.fy, rel=0.01)
    assert cam.cx == pytest.approx(TRUE.cx, rel=0.01)
    assert cam.cy == pytest.approx(TRUE.cy, rel=0.01)
    assert (cam.width, cam.height) == (1280, 800)
    assert len(result.per_image_rms_px) == 10 and result.rejected == ()
    assert result.rms_px < 0.3 and max(result.per_image_rms_px) < 0.5


def test_with_distortion_model_and_rejected_images() -> None:
    board = chessboard(9, 6, 25.0)
    poses = board_views(board, 12, seed=12)
    images = [render_board(board, TRUE, T, noise_sigma=1.0, seed=k) for k, T in enumerate(poses)]
    blank = np.full((800, 1280), 128, np.uint8)
    result = calibrate_intrinsics(board, [blank, *images], distortion=True)
    assert result.rejected == (0,) and result.used == tuple(range(1, 13))
    assert result.camera.fx == pytest.approx(TRUE.fx, rel=0.01)
    assert result.camera.cy == pytest.approx(TRUE.cy, rel=0.01)
    assert np.all(np.abs(result.camera.dist[:2]) < 0.05)  # true lens has none
    # each returned board pose matches the rendered one
    for T_est, T_true in zip(result.T_camera_board, poses, strict=True):
        d_mm, d_deg = pose_distance(T_est, T_true)
        assert d_mm < 3.0 and d_deg < 0.3


def test_too_few_views_and_mixed_sizes_are_refused() -> None:
    board = chessboard(9, 6, 25.0)
    images = [render_board(board, TRUE, T) for T in board_views(board, 2, seed=13)]
    with pytest.raises(IntrinsicsError, match="need at least 3"):
        calibrate_intrinsics(board, images)
    with pytest.raises(IntrinsicsError, match="differ in size"):
        calibrate_intrinsics(board, [images[0], images[1][:400]])
    with pytest.raises(IntrinsicsError, match="no images"):
        calibrate_intrinsics(board, [])


def test_chessboard_pose_is_canonical_however_the_board_is_turned() -> None:
    """Rendered with the board turned 180 deg in the image, the pose still comes out right."""
    board = chessboard(9, 6, 25.0)
    centre = board.object_points_mm().mean(axis=0)
    for yaw in (0.1, np.pi - 0.1, np.pi + 0.3, -0.4):
        R = Rotation.from_rotvec([0.2, -0.15, yaw]).as_matrix()
        T = make_T(R, np.array([10.0, -5.0, 600.0]) - R @ centre)
        img = render_board(board, TRUE, T, noise_sigma=1.0)
        pts = detect_board(board, img)
        assert pts is not None
        est = board_pose(board, pts, TRUE)
        d_mm, d_deg = pose_distance(est.T_camera_board, T)
        assert d_mm < 1.0 and d_deg < 0.1, (yaw, d_mm, d_deg)
        assert est.rms_px < 0.3


def test_board_model_validation() -> None:
    with pytest.raises(ValueError, match="kind"):
        Board("hexagons", 4, 4, 10.0)  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="pitch_mm"):
        Board("chessboard", 9, 6, 0.0)
    pts = Board("acircles", 4, 3, 40.0).object_points_mm()
    assert pts[1, 0] - pts[0, 0] == pytest.approx(40.0)  # spacing along a row
    assert pts[4, 0] - pts[0, 0] == pytest.approx(20.0)  # next row shifted by half


def test_circle_grid_focal_length_without_the_perspective_bias_of_dot_centroids() -> None:
    """A circle grid's points are the dots' image centroids, off the images of their centres
    by a perspective bias that shortens the focal length; with the dots' diameter it is
    corrected (the rendered dots are half the pitch across)."""
    board = Board("circles", 7, 5, 30.0)
    images = [render_board(board, TRUE, T, noise_sigma=0.5, seed=k)
              for k, T in enumerate(board_views(board, 12, seed=5))]
    plain = calibrate_intrinsics(board, images, distortion=False).camera
    corrected = calibrate_intrinsics(board, images, distortion=False,
                                     dot_diameter_mm=15.0).camera
    plain_err = abs(plain.fx / TRUE.fx - 1.0) + abs(plain.fy / TRUE.fy - 1.0)
    corrected_err = abs(corrected.fx / TRUE.fx - 1.0) + abs(corrected.fy / TRUE.fy - 1.0)
    print(f"focal error: {plain_err:.2e} centroids, {corrected_err:.2e} corrected")
    assert corrected_err < 0.5 * plain_err
