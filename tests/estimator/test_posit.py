"""POSIT and coplanar POSIT as raw seeds: convergence, exactness on ideal data, typed failures."""

from __future__ import annotations

import dataclasses
import sys

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from estimator import (
    BehindCameraError,
    CameraModel,
    DegenerateGeometryError,
    PositResult,
    TooFewBlobsError,
    posit,
    solve_pose,
)
from estimator.transforms import make_T, pose_distance
from tests.support.pose_scenes import CAM, CAM_DISTORTED, FLAT, SOLID


def _tilted(rng: np.random.Generator, tilt_deg: tuple[float, float]) -> np.ndarray:
    """Random in-plane spin, then a tilt of the plate out of the image plane."""
    axis = np.r_[rng.normal(size=2), 0.0]
    axis /= np.linalg.norm(axis)
    tilt = np.radians(rng.uniform(*tilt_deg))
    spin = Rotation.from_rotvec([0.0, 0.0, rng.uniform(-np.pi, np.pi)])
    return (Rotation.from_rotvec(axis * tilt) * spin).as_matrix()


def _scene(
    rng: np.random.Generator, obj: np.ndarray, tilt_deg: tuple[float, float],
    range_mm: tuple[float, float], cam: CameraModel = CAM,
) -> tuple[np.ndarray, np.ndarray]:
    R = _tilted(rng, tilt_deg)
    t = np.r_[rng.uniform(-80, 80, 2), rng.uniform(*range_mm)] - R @ obj.mean(axis=0)
    T = make_T(R, t)
    return T, cam.project(obj @ R.T + t)


@pytest.mark.parametrize("cam", [CAM, CAM_DISTORTED], ids=["pinhole", "distorted"])
def test_posit_converges_to_the_exact_pose_on_well_conditioned_solids(cam: CameraModel) -> None:
    rng = np.random.default_rng(11)
    for _ in range(100):
        T, img = _scene(rng, SOLID, (0, 70), (500, 1200), cam)
        result = posit(SOLID, img, cam)
        assert result.converged and result.iterations < 30
        dt_mm, dr_deg = pose_distance(result.T_camera_target, T)
        assert dt_mm < 1e-3 and dr_deg < 1e-4
        assert result.rms_px < 1e-3
        assert result.alternative is None


def test_coplanar_posit_converges_on_tilted_plates_and_keeps_the_other_branch() -> None:
    rng = np.random.default_rng(12)
    distinct = 0
    for _ in range(100):
        T, img = _scene(rng, FLAT, (20, 60), (500, 900))
        result = posit(FLAT, img, CAM)
        assert result.converged and result.iterations < 30
        dt_mm, dr_deg = pose_distance(result.T_camera_target, T)
        assert dt_mm < 1e-2 and dr_deg < 1e-3
        if result.alternative is not None:  # None only when both branches merged
            T_alt, rms_alt = result.alternative
            assert rms_alt > result.rms_px
            assert pose_distance(T_alt, T)[1] > 0.1  # a genuinely different (mirrored) pose
            distinct += 1
    assert distinct >= 80


def test_posit_with_noise_is_close() -> None:
    rng = np.random.default_rng(13)
    errors = []
    for obj in (SOLID, FLAT):
        for _ in range(50):
            T, img = _scene(rng, obj, (20, 50), (500, 800))
            result = posit(obj, img + rng.normal(0.0, 0.3, img.shape), CAM)
            errors.append(pose_distance(result.T_camera_target, T))
    dt, dr = np.array(errors).T
    assert np.median(dt) < 3.0 and np.median(dr) < 1.0


def test_rotation_is_orthonormal_and_result_frozen() -> None:
    rng = np.random.default_rng(14)
    _, img = _scene(rng, SOLID, (10, 40), (300, 400))
    result = posit(SOLID, img + rng.normal(0.0, 1.0, img.shape), CAM, max_iterations=3)
    R = result.T_camera_target[:3, :3]
    assert np.allclose(R @ R.T, np.eye(3), atol=1e-12)
    assert np.isclose(np.linalg.det(R), 1.0)
    assert result.iterations == 3 and not result.converged
    with pytest.raises(dataclasses.FrozenInstanceError):
        result.iterations = 5  # type: ignore[misc]
    assert isinstance(result, PositResult)


def test_object_matrix_is_computed_once_per_model() -> None:
    posit_module = sys.modules["estimator.posit"]
    first = posit_module.object_model(SOLID)
    assert posit_module.object_model(SOLID.copy()) is first
    assert first.object_matrix.shape == (3, len(SOLID) - 1)


def test_wrong_fixed_point_at_close_range() -> None:
    """Strong perspective (target as deep as it is far): POSIT converges to a wrong pose."""
    T = make_T(Rotation.from_rotvec([-0.4741, 0.5145, -0.1321]).as_matrix(), [-33.37, -3.22, 65.8])
    img = CAM.project(SOLID @ T[:3, :3].T + T[:3, 3])
    result = posit(SOLID, img, CAM)
    assert result.converged
    assert pose_distance(result.T_camera_target, T)[1] > 10.0
    assert result.rms_px > 100.0


def test_coplanar_posit_walks_away_from_a_near_frontal_plate_and_solve_pose_recovers() -> None:
    """A plate tilted 8 deg, noise-free: the true pose is a fixed point of coplanar POSIT, but
    a repelling one (near-frontal plates make the out-of-plane component a square root of a
    vanishing quantity), so the iteration converges elsewhere, 30 deg off; neither branch is
    right. solve_pose's refinement and second-minimum search still land on the exact pose."""
    plate = np.array([[114.055644, 12.974365, 0.0], [50.799174, 74.493233, 0.0],
                      [49.103896, 49.463432, 0.0], [3.307094, 67.81618, 0.0],
                      [64.577198, 29.675854, 0.0], [94.611444, 27.287535, 0.0]])
    camera = CameraModel(800.0, 800.0, 639.5, 399.5, width=1280, height=800)
    T = make_T(Rotation.from_rotvec([0.107317, 0.113399, -1.490715]).as_matrix(),
               [-155.917944, 54.021709, 621.440249])
    img = camera.project(plate @ T[:3, :3].T + T[:3, 3])
    seed = posit(plate, img, camera)
    assert seed.converged
    assert pose_distance(seed.T_camera_target, T)[1] > 20.0
    assert seed.alternative is not None
    assert pose_distance(seed.alternative[0], T)[1] > 5.0
    result = solve_pose(plate, img, camera)
    dt_mm, dr_deg = pose_distance(result.T_camera_target, T)
    assert dt_mm < 1e-6 and dr_deg < 1e-6


def test_too_few_points() -> None:
    with pytest.raises(TooFewBlobsError) as info:
        posit(SOLID[:3], np.zeros((3, 2)), CAM)
    assert info.value.found == 3 and info.value.needed == 4


def test_collinear_model() -> None:
    line = np.array([[0, 0, 0], [10, 0, 0], [20, 0, 0], [35, 0, 0]], float)
    with pytest.raises(DegenerateGeometryError, match="collinear"):
        posit(line, np.array([[0, 0], [10, 1], [20, 3], [30, 5]], float), CAM)


def test_collinear_image() -> None:
    img = np.column_stack((np.linspace(100, 600, 6), np.linspace(200, 300, 6)))
    with pytest.raises(DegenerateGeometryError, match="image points"):
        posit(SOLID, img, CAM)


def test_target_behind_camera() -> None:
    """Close range: with point 0 as reference, POSIT's fixed point puts dots behind the lens."""
    T = make_T(Rotation.from_rotvec([-0.1888, 0.6829, -0.0665]).as_matrix(), [-0.85, -16.4, 66.3])
    img = CAM.project(SOLID @ T[:3, :3].T + T[:3, 3])
    with pytest.raises(BehindCameraError) as info:
        posit(SOLID, img, CAM)
    assert info.value.code == "target_behind_camera"


def test_bad_shapes_are_value_errors() -> None:
    with pytest.raises(ValueError, match="5 image points for 6"):
        posit(SOLID, np.zeros((5, 2)), CAM)
    with pytest.raises(ValueError, match="shape"):
        posit(SOLID[:, :2], np.zeros((6, 2)), CAM)
