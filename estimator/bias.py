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

import numba
import numpy as np
from numpy.typing import ArrayLike, NDArray

from estimator.arrays import kernel_array
from estimator.camera import CameraModel


def _plane_bases(normals: NDArray[np.float64]) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Two unit vectors spanning each dot's plane (any orientation: a circle has no preferred
    in-plane axis)."""
    n = normals / np.linalg.norm(normals, axis=1, keepdims=True)
    helper = np.where(np.abs(n[:, :1]) < 0.9, [[1.0, 0.0, 0.0]], [[0.0, 1.0, 0.0]])
    e1 = helper - np.sum(helper * n, axis=1, keepdims=True) * n
    e1 /= np.linalg.norm(e1, axis=1, keepdims=True)
    return e1, np.cross(n, e1)


@numba.njit(cache=True, nogil=True)
def _plate_centre_and_centroid(
    T: NDArray[np.float64], P: NDArray[np.float64], r2: float
) -> NDArray[np.float64]:
    """:func:`centre_and_centroid_normalised` for dots in the target's z = 0 plane ->
    (N,4): projected centre (x, y), ellipse centroid (x, y); all NaN when a dot centre is
    behind the camera. The plane axes a, b are the target's x and y axes, shared by every
    dot, so per dot only its centre c enters: centroid ~ (a a_z + b b_z) - c c_z / r^2.
    """
    n = P.shape[0]
    out = np.empty((n, 4))
    ab = np.empty(3)
    for k in range(3):
        ab[k] = T[k, 0] * T[2, 0] + T[k, 1] * T[2, 1]
    for i in range(n):
        c0 = T[0, 0] * P[i, 0] + T[0, 1] * P[i, 1] + T[0, 2] * P[i, 2] + T[0, 3]
        c1 = T[1, 0] * P[i, 0] + T[1, 1] * P[i, 1] + T[1, 2] * P[i, 2] + T[1, 3]
        c2 = T[2, 0] * P[i, 0] + T[2, 1] * P[i, 1] + T[2, 2] * P[i, 2] + T[2, 3]
        if c2 <= 0.0:
            out[:] = np.nan
            return out
        w = c2 / r2
        h0, h1, h2 = ab[0] - c0 * w, ab[1] - c1 * w, ab[2] - c2 * w
        out[i, 0], out[i, 1] = c0 / c2, c1 / c2
        out[i, 2], out[i, 3] = h0 / h2, h1 / h2
    return out


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
    r2 = (0.5 * dot_diameter_mm) ** 2
    if normals is None:  # the target's own x and y axes span every dot's plane (compiled)
        both = _plate_centre_and_centroid(kernel_array(T), kernel_array(P), r2)
        if len(both) and not np.isfinite(both[0, 0]):
            raise ValueError("a dot centre is behind the camera")
        return both[:, :2], both[:, 2:]
    R = T[:3, :3]
    c = P @ R.T + T[:3, 3]
    if c[:, 2].min() <= 0.0:
        raise ValueError("a dot centre is behind the camera")
    # Homography columns per dot, in the camera frame: the plane axes a, b and the centre c.
    # Ellipse centre = H diag(1, 1, -1/r^2) H^T e3; H^T e3 is the third row (a_z, b_z, c_z).
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
