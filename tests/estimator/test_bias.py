"""Perspective bias of dot centroids, checked against brute-force integration of imaged discs."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from estimator import CameraModel, solve_pose
from estimator.bias import centroid_bias_px, correct_image_points
from estimator.transforms import make_T, pose_distance

CAM = CameraModel(900.0, 880.0, 640.0, 400.0)
DIAMETER_MM = 20.0


def _plane_axes(normal: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    n = normal / np.linalg.norm(normal)
    a = np.cross(n, [0.3, 0.5, 0.8])
    a /= np.linalg.norm(a)
    return a, np.cross(n, a)


def _disc_centroid_quadrature(
    T: np.ndarray, centre: np.ndarray, normal: np.ndarray, radius: float
) -> np.ndarray:
    """Image-area-weighted centroid of the imaged disc, by quadrature over the disc (px).

    Uniform samples on the disc must be weighted by the local image-area magnification
    |dx/d(a,b)| = |det H| / w^3 of the plane-to-image homography: an unweighted mean of projected
    disc points is *not* the image centroid.
    """
    a, b = _plane_axes(normal)
    nodes, weights = np.polynomial.legendre.leggauss(48)
    rho = 0.5 * radius * (nodes + 1.0)
    w_rho = 0.5 * radius * weights * rho
    theta = np.linspace(0.0, 2.0 * np.pi, 256, endpoint=False)
    rr, tt = np.meshgrid(rho, theta)
    ww = np.meshgrid(w_rho, theta)[0]
    pts = centre + rr[..., None] * (np.cos(tt)[..., None] * a + np.sin(tt)[..., None] * b)
    cam_pts = pts.reshape(-1, 3) @ T[:3, :3].T + T[:3, 3]
    H = np.column_stack((T[:3, :3] @ a, T[:3, :3] @ b, T[:3, :3] @ centre + T[:3, 3]))
    weight = ww.ravel() * abs(np.linalg.det(H)) / cam_pts[:, 2] ** 3
    xy = cam_pts[:, :2] / cam_pts[:, 2:3]
    mean = (weight[:, None] * xy).sum(axis=0) / weight.sum()
    return np.array([CAM.fx * mean[0] + CAM.cx, CAM.fy * mean[1] + CAM.cy])


def _disc_centroid_raster(
    cam: CameraModel, T: np.ndarray, centre: np.ndarray, radius: float
) -> np.ndarray:
    """Centroid of the image points (a 0.01 px grid) whose ray hits the disc (z=0 plane)."""
    c_px = cam.project((T[:3, :3] @ centre + T[:3, 3])[None])[0]
    half = 16.0
    step = 0.01
    g = np.arange(-half, half, step) + step / 2
    R, t = T[:3, :3], T[:3, 3]
    n_cam = R[:, 2]  # target z axis in the camera frame
    plane = n_cam @ (R @ centre + t)
    total, count = np.zeros(2), 0
    for rows in np.array_split(g, 32):  # a band of image rows at a time: bounded memory
        uu, vv = np.meshgrid(c_px[0] + g, c_px[1] + rows)
        rays = np.stack(((uu - cam.cx) / cam.fx, (vv - cam.cy) / cam.fy, np.ones_like(uu)),
                        axis=-1)
        hit = rays * (plane / (rays @ n_cam))[..., None]
        local = (hit - t) @ R  # back into the target frame
        inside = np.sum((local - centre) ** 2, axis=-1) <= radius**2
        edges = (inside[:, 0], inside[:, -1], inside[0] if rows[0] == g[0] else False,
                 inside[-1] if rows[-1] == g[-1] else False)
        assert not any(np.any(e) for e in edges), "raster window too small"
        total += (uu[inside].sum(), vv[inside].sum())
        count += int(inside.sum())
    return total / count


def _tilted_pose() -> np.ndarray:
    R = Rotation.from_euler("xyz", [50.0, -25.0, 10.0], degrees=True).as_matrix()
    return make_T(R, [60.0, -40.0, 180.0])


def test_bias_matches_quadrature_for_many_dots() -> None:
    T = _tilted_pose()
    dots = np.array([[0.0, 0.0, 0.0], [40.0, 0.0, 0.0], [-30.0, 25.0, 0.0], [10.0, -35.0, 0.0]])
    bias = centroid_bias_px(T, dots, DIAMETER_MM, CAM)
    projected = CAM.project(dots @ T[:3, :3].T + T[:3, 3])
    for k, dot in enumerate(dots):
        centroid = _disc_centroid_quadrature(T, dot, np.array([0, 0, 1.0]), DIAMETER_MM / 2)
        assert np.allclose(projected[k] + bias[k], centroid, atol=1e-6)
    assert np.max(np.abs(bias)) > 0.1  # a real effect at this size and tilt, not a no-op


def test_bias_matches_pixel_raster() -> None:
    """Independent of the homography algebra: sample the image, back-project, test the disc.

    A wide-angle camera keeps the imaged dot ~25 px across so a 0.01 px grid stays small.
    """
    cam = CameraModel(200.0, 200.0, 320.0, 200.0, width=640, height=400)
    T = _tilted_pose()
    dot = np.array([15.0, -10.0, 0.0])
    bias = centroid_bias_px(T, dot[None], DIAMETER_MM, cam)[0]
    projected = cam.project((T[:3, :3] @ dot + T[:3, 3])[None])[0]
    raster = _disc_centroid_raster(cam, T, dot, DIAMETER_MM / 2)
    assert np.allclose(projected + bias, raster, atol=1e-3), (projected + bias, raster)
    assert np.max(np.abs(bias)) > 0.02


def test_custom_normals_match_quadrature() -> None:
    """Dots on different faces of a non-planar target, each with its own plane normal."""
    T = make_T(Rotation.from_rotvec([0.3, -0.4, 0.2]).as_matrix(), [-20.0, 30.0, 250.0])
    dots = np.array([[0.0, 0.0, 0.0], [30.0, 0.0, -20.0], [0.0, 40.0, -10.0]])
    normals = np.array([[0.0, 0.0, 1.0], [0.6, 0.0, 0.8], [0.0, -0.5, 1.0]])
    bias = centroid_bias_px(T, dots, DIAMETER_MM, CAM, normals=normals)
    projected = CAM.project(dots @ T[:3, :3].T + T[:3, 3])
    for k in range(3):
        centroid = _disc_centroid_quadrature(T, dots[k], normals[k], DIAMETER_MM / 2)
        assert np.allclose(projected[k] + bias[k], centroid, atol=1e-6)


def test_no_bias_for_a_fronto_parallel_dot_on_the_axis() -> None:
    T = make_T(np.eye(3), [0.0, 0.0, 300.0])
    cam = CameraModel(900.0, 900.0, 640.0, 400.0)
    bias = centroid_bias_px(T, np.zeros((1, 3)), DIAMETER_MM, cam)
    assert np.allclose(bias, 0.0, atol=1e-12)


def test_correct_image_points_subtracts_the_bias() -> None:
    T = _tilted_pose()
    dots = np.array([[0.0, 0.0, 0.0], [40.0, 0.0, 0.0]])
    measured = np.array([[700.0, 300.0], [750.0, 320.0]])
    bias = centroid_bias_px(T, dots, DIAMETER_MM, CAM)
    assert np.allclose(correct_image_points(measured, T, dots, DIAMETER_MM, CAM), measured - bias)


def test_bad_diameter_is_rejected() -> None:
    with pytest.raises(ValueError, match="dot_diameter_mm"):
        centroid_bias_px(_tilted_pose(), np.zeros((1, 3)), 0.0, CAM)


def test_solve_pose_with_bias_correction_recovers_the_pose_from_centroids() -> None:
    """Image points are the true dot centroids (biased); correcting makes the pose exact."""
    rng = np.random.default_rng(5)
    dots = np.array(
        [[0, 0, 0], [60, 0, 0], [0, 60, 0], [60, 60, 0], [30, 90, 0], [-20, 40, 0]], float
    )
    before, after = [], []
    for _ in range(20):
        R = Rotation.from_euler("xyz", rng.uniform(-45, 45, 3), degrees=True).as_matrix()
        T = make_T(R, [rng.uniform(-40, 0), rng.uniform(-40, 0), rng.uniform(180, 300)])
        centroids = CAM.project(dots @ R.T + T[:3, 3]) + centroid_bias_px(
            T, dots, DIAMETER_MM, CAM
        )
        plain = solve_pose(dots, centroids, CAM)
        corrected = solve_pose(dots, centroids, CAM, dot_diameter_mm=DIAMETER_MM)
        before.append(pose_distance(plain.T_camera_target, T)[0])
        after.append(pose_distance(corrected.T_camera_target, T)[0])
        assert corrected.image_points_px is not None
        assert any("perspective bias" in n for n in corrected.notes)
    # One correction at the (slightly biased) first pose leaves a second-order remainder only.
    assert np.mean(after) < 0.05 * np.mean(before)
    assert max(after) < 0.01
