"""Maximum-likelihood refinement of a pose seed on the pixel reprojection error.

With Gaussian centroid noise the maximum-likelihood pose minimises the summed squared pixel
reprojection error; OpenCV's Levenberg-Marquardt (``cv2.solvePnPRefineLM``) does that, through
the real distortion model. Its pose parameters are OpenCV's (rotation vector, translation), so
the conversions at this boundary use ``cv2.Rodrigues`` -- the same library's own definition of
that vector, and an order of magnitude cheaper per call than a SciPy ``Rotation`` round trip.

LM's own stopping rule ends while the pose can still drift along flat directions of the cost
(about 1e-3 mm / 1e-3 deg for a planar target, depending on where it started), and started at
the minimum it spends its whole iteration budget rejecting steps (~3x the cost of a normal
run). So a pose that is already close -- after the perspective-bias correction, or from the
tracked pose -- is finished with OpenCV's Gauss-Newton (``cv2.solvePnPRefineVVS``, full steps):
it converges in two or three steps to 1e-9 mm, whatever the start, so a refinement from the
tracked pose lands on the minimum a full solve would reach. VVS works on undistorted
normalised coordinates; with fx = fy and no distortion that is the same cost, and with
distortion its minimum differs from the pixel one by about 1 % of the noise-induced pose error
(measured with -0.12 k1).
"""

from __future__ import annotations

import functools
from typing import Any

import cv2
import numpy as np
from numpy.typing import ArrayLike, NDArray

from estimator.camera import CameraModel

_LM_CRITERIA = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_COUNT, 30, 1e-12)
_GN_CRITERIA = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_COUNT, 20, 1e-12)
_UNDISTORT = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_COUNT, 50, 1e-15)
_NO_DISTORTION = np.zeros(5)


@functools.lru_cache(maxsize=16)
def camera_arrays(camera: CameraModel) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """The camera's K and OpenCV distortion array, made once per camera (read-only: shared)."""
    K, dist = camera.K, camera.dist_coeffs
    K.flags.writeable = False
    dist.flags.writeable = False
    return K, dist


def _as_T(rvec: NDArray[np.float64], tvec: NDArray[np.float64]) -> NDArray[np.float64]:
    T = np.eye(4)
    T[:3, :3] = cv2.Rodrigues(rvec)[0]
    T[:3, 3] = tvec.reshape(3)
    return T


def reprojection(
    object_points_mm: NDArray[np.float64],
    image_points_px: NDArray[np.float64],
    K: NDArray[np.float64],
    dist: NDArray[np.float64],
    rvec: NDArray[np.float64],
    tvec: NDArray[np.float64],
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """(projection minus measurement (N,2) px, Jacobian (2N,6) over rvec then tvec)."""
    projected, jacobian = cv2.projectPoints(object_points_mm, rvec, tvec, K, dist)
    residuals = np.asarray(projected, dtype=np.float64).reshape(-1, 2) - image_points_px
    return residuals, np.asarray(jacobian[:, :6], dtype=np.float64)


def covariance_from(residuals: NDArray[np.float64], J: NDArray[np.float64]) -> NDArray[np.float64]:
    """sigma^2 (J^T J)^-1 with sigma^2 = sum r^2 / (2N - 6), the unbiased noise estimate.

    Inverted by Cholesky (J^T J is symmetric positive definite for any pose the target
    determines); a pseudo-inverse when that fails keeps it finite for a near-singular
    configuration (huge variances there are the honest answer).
    """
    dof = residuals.size - 6
    sigma2 = float(np.sum(residuals * residuals)) / dof if dof > 0 else float("nan")
    JtJ = J.T @ J
    ok, inverse = cv2.invert(JtJ, flags=cv2.DECOMP_CHOLESKY)  # 5x cheaper than an SVD
    if not ok or not np.all(np.isfinite(inverse)):
        inverse = np.linalg.pinv(JtJ)
    return np.asarray(sigma2 * inverse, dtype=np.float64)


def refine_pose(
    object_points_mm: ArrayLike,
    image_points_px: ArrayLike,
    camera: CameraModel,
    T_init: ArrayLike,
) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
    """Levenberg-Marquardt refinement of ``T_init`` (4x4 mm) on the pixel reprojection error.

    Returns ``(T_camera_target,
    residuals_px (N,), covariance (6,6))``: residuals are the per-point pixel distances, and the
    covariance is sigma^2 (J^T J)^-1 from the final Jacobian, parameters ordered as rotation
    vector (rad, x y z) then translation (mm, x y z), noise estimated from the residuals.
    """
    obj = np.ascontiguousarray(object_points_mm, dtype=float).reshape(-1, 3)
    img = np.ascontiguousarray(image_points_px, dtype=float).reshape(-1, 2)
    T0 = np.asarray(T_init, dtype=float)
    T, residuals, J = refine_arrays(obj, img, camera.K, camera.dist_coeffs, T0)
    return T, np.sqrt((residuals * residuals).sum(axis=1)), covariance_from(residuals, J)


def refine_arrays(
    obj: NDArray[np.float64],
    img: NDArray[np.float64],
    K: NDArray[np.float64],
    dist: NDArray[np.float64],
    T_init: NDArray[np.float64],
) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
    """The LM step on prepared arrays -> (T, residual vectors (N,2) px, Jacobian (2N,6)).

    rvec/tvec must be (3,1): with flat (3,) arrays ``solvePnPRefineLM`` silently returns its
    input unchanged (OpenCV 5.0).
    """
    rvec = cv2.Rodrigues(T_init[:3, :3])[0]
    tvec = T_init[:3, 3].reshape(3, 1).copy()
    rvec_out, tvec_out = cv2.solvePnPRefineLM(obj, img, K, dist, rvec, tvec, _LM_CRITERIA)
    r = np.asarray(rvec_out, dtype=np.float64)
    t = np.asarray(tvec_out, dtype=np.float64)
    residuals, J = reprojection(obj, img, K, dist, r, t)
    return _as_T(r, t), residuals, J


def polish_arrays(
    obj: NDArray[np.float64],
    img: NDArray[np.float64],
    K: NDArray[np.float64],
    dist: NDArray[np.float64],
    T_init: NDArray[np.float64],
) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
    """Gauss-Newton from a pose already near the minimum (see the module docstring) ->
    (T, residual vectors (N,2) px, Jacobian (2N,6)), like :func:`refine_arrays`."""
    rvec = cv2.Rodrigues(T_init[:3, :3])[0]
    tvec = T_init[:3, 3].reshape(3, 1).copy()
    ideal: NDArray[Any] = img
    if dist.any():  # undistort to full precision first (VVS's own default stops at ~1e-6)
        ideal = cv2.undistortPoints(img.reshape(-1, 1, 2), K, dist, P=K, criteria=_UNDISTORT)
    rvec_out, tvec_out = cv2.solvePnPRefineVVS(
        obj, ideal, K, _NO_DISTORTION, rvec, tvec, _GN_CRITERIA, 1.0)
    r = np.asarray(rvec_out, dtype=np.float64)
    t = np.asarray(tvec_out, dtype=np.float64)
    residuals, J = reprojection(obj, img, K, dist, r, t)
    return _as_T(r, t), residuals, J
