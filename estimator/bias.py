"""Perspective bias of dot centroids: the image centroid of a circle is not its centre's image.

A circle of radius r on a plane images, through the plane-to-image homography H, to an ellipse
(the conic H^-T diag(1, 1, -r^2) H^-1). A blob detector measures the centroid of that filled
ellipse, which is the ellipse's centre -- the pole of the line at infinity, H diag(1, 1, -1/r^2)
H^T (0, 0, 1) -- and that point is not the projection H (0, 0, 1) of the circle's centre. The
difference grows with the dot size and the tilt and is a systematic error a pose solver cannot
average away, so with a pose in hand we compute it per dot and subtract it.

The offset is computed exactly in undistorted normalised coordinates. With lens distortion both
points are then distorted and subtracted, which neglects the curvature of the distortion across
one dot (second order in the dot's image size).
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray

from estimator.camera import CameraModel


def _plane_bases(normals: NDArray[np.float64]) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Two unit vectors spanning each dot's plane (any orientation: a circle has no preferred
    in-plane axis)."""
    n = normals / np.linalg.norm(normals, axis=1, keepdims=True)
    helper = np.where(np.abs(n[:, :1]) < 0.9, [[1.0, 0.0, 0.0]], [[0.0, 1.0, 0.0]])
    e1 = helper - np.sum(helper * n, axis=1, keepdims=True) * n
    e1 /= np.linalg.norm(e1, axis=1, keepdims=True)
    return e1, np.cross(n, e1)


def centre_and_centroid_normalised(
    T_camera_target: ArrayLike,
    object_points_mm: ArrayLike,
    dot_diameter_mm: float,
    normals: ArrayLike | None = None,
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """(projected centres, ellipse centroids), each (N,2) in normalised image coordinates."""
    T = np.asarray(T_camera_target, dtype=float)
    P = np.asarray(object_points_mm, dtype=float).reshape(-1, 3)
    if not dot_diameter_mm > 0:
        raise ValueError(f"dot_diameter_mm must be positive, got {dot_diameter_mm}")
    R = T[:3, :3]
    c = P @ R.T + T[:3, 3]
    if c[:, 2].min() <= 0.0:
        raise ValueError("a dot centre is behind the camera")
    r2 = (0.5 * dot_diameter_mm) ** 2
    # Homography columns per dot, in the camera frame: the plane axes a, b and the centre c.
    # Ellipse centre = H diag(1, 1, -1/r^2) H^T e3; H^T e3 is the third row (a_z, b_z, c_z).
    if normals is None:  # the target's own x and y axes span every dot's plane: a, b shared
        ab = R[:, 0] * R[2, 0] + R[:, 1] * R[2, 1]
    else:
        n = np.broadcast_to(np.asarray(normals, dtype=float), P.shape)
        e1, e2 = _plane_bases(np.asarray(n, dtype=float))
        a = e1 @ R.T
        b = e2 @ R.T
        ab = a * a[:, 2:3] + b * b[:, 2:3]
    centre_h = ab - c * (c[:, 2:3] / r2)
    centroid = centre_h[:, :2] / centre_h[:, 2:3]
    return c[:, :2] / c[:, 2:3], centroid


def centroid_bias_px(
    T_camera_target: ArrayLike,
    object_points_mm: ArrayLike,
    dot_diameter_mm: float,
    camera: CameraModel,
    normals: ArrayLike | None = None,
) -> NDArray[np.float64]:
    """(N,2) px: image centroid of each imaged dot minus the projection of its centre.

    ``normals`` are the dots' plane normals in the target frame, (3,) or (N,3); by default every
    dot lies in the target's z = 0 plane (normal = target z axis).
    """
    centre, centroid = centre_and_centroid_normalised(
        T_camera_target, object_points_mm, dot_diameter_mm, normals
    )
    if not camera.has_distortion:
        return (centroid - centre) * np.array([camera.fx, camera.fy])
    both = camera.distort_points(np.vstack((centroid, centre)))
    n = len(centre)
    return both[:n] - both[n:]


def correct_image_points(
    image_points_px: ArrayLike,
    T_camera_target: ArrayLike,
    object_points_mm: ArrayLike,
    dot_diameter_mm: float,
    camera: CameraModel,
    normals: ArrayLike | None = None,
) -> NDArray[np.float64]:
    """Measured dot centroids minus their perspective bias: estimates of the centres' images."""
    bias = centroid_bias_px(T_camera_target, object_points_mm, dot_diameter_mm, camera, normals)
    return np.asarray(image_points_px, dtype=float).reshape(-1, 2) - bias
