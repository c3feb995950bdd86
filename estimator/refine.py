"""Maximum-likelihood refinement of a pose seed on the pixel reprojection error.

With Gaussian centroid noise the maximum-likelihood pose minimises the summed squared pixel
reprojection error. MINPACK's Levenberg-Marquardt (``lmder``, through SciPy) minimises it here,
with the residuals and their analytic Jacobian from ``cv2.projectPoints`` -- the real distortion
model, so the minimum is the pixel one with or without lens distortion.

The unknown is a correction applied on the left of the start pose, X = R(delta) (R0 P + t0) +
tau: delta starts at zero, so the rotation vector never nears its singularity at pi whatever
the start, and ``projectPoints`` of the start-frame points gives exactly the Jacobian over
(delta, tau) that LM needs. The covariance is then taken at the final pose over OpenCV's
(rotation vector, translation) of the pose itself, the convention of :class:`PoseResult`.

Why MINPACK and why its compiled entry point: on 4-12 points one ``lmder`` run costs a few
``projectPoints`` calls (~5 us each), while ``cv2.solvePnPRefineLM`` spends 12-25 us per
iteration in OpenCV 5 (60-130 us per call) and ``scipy.optimize.leastsq`` wraps the same
``lmder`` in ~50 us of argument checks and message formatting per call -- three times the solve
itself, paid two or three times per frame. So ``lmder`` is called directly and ``leastsq`` is
the fallback should a SciPy release rename it (slower, same result; a test notices). MINPACK
stops on relative reduction (``ftol``) and step size (``xtol``); from a pose already at the
minimum it returns after a few evaluations, so the same routine serves both the refinement of
a POSIT seed and the finish from a tracked pose.
"""

from __future__ import annotations

import functools
from collections.abc import Callable
from typing import Any

import cv2
import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.optimize import leastsq

from estimator.camera import CameraModel

try:  # MINPACK's lmder without leastsq's per-call checks (see the module docstring)
    from scipy.optimize._minpack import _lmder as _LMDER
except ImportError:  # pragma: no cover - depends on the SciPy release
    _LMDER = None

FAST_PATH = _LMDER is not None
TOLERANCE = 1e-8  # relative reduction of the squared error and relative step at which LM stops
MAX_EVALUATIONS = 200
_STEP_BOUND = 100.0  # MINPACK's ``factor``: initial step bound (its default)
_BOTTOM_ROW = np.array([0.0, 0.0, 0.0, 1.0])


@functools.lru_cache(maxsize=16)
def camera_arrays(camera: CameraModel) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """The camera's K and OpenCV distortion array, made once per camera (read-only: shared)."""
    K, dist = camera.K, camera.dist_coeffs
    K.flags.writeable = False
    dist.flags.writeable = False
    return K, dist


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
    if not ok or not np.isfinite(inverse).all():
        inverse = np.linalg.pinv(JtJ)
    return np.asarray(sigma2 * inverse, dtype=np.float64)


def refine_pose(
    object_points_mm: ArrayLike,
    image_points_px: ArrayLike,
    camera: CameraModel,
    T_init: ArrayLike,
) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
    """Levenberg-Marquardt refinement of ``T_init`` (4x4 mm) on the pixel reprojection error.

    Returns ``(T_camera_target, residuals_px (N,), covariance (6,6))``: residuals are the
    per-point pixel distances, and the covariance is sigma^2 (J^T J)^-1 from the final
    Jacobian, parameters ordered as rotation vector (rad, x y z) then translation (mm, x y z),
    noise estimated from the residuals.
    """
    obj = np.ascontiguousarray(object_points_mm, dtype=float).reshape(-1, 3)
    img = np.ascontiguousarray(image_points_px, dtype=float).reshape(-1, 2)
    T0 = np.asarray(T_init, dtype=float)
    K, dist = camera_arrays(camera)
    T, residuals, J = refine_arrays(obj, img, K, dist, T0)
    return T, np.sqrt((residuals * residuals).sum(axis=1)), covariance_from(residuals, J)


def _correction_problem(
    points_cam: NDArray[np.float64], target_px: NDArray[np.float64], K: NDArray[np.float64],
    dist: NDArray[np.float64],
) -> tuple[Callable[[NDArray[np.float64]], NDArray[np.float64]],
           Callable[[NDArray[np.float64]], NDArray[np.float64]],
           Callable[[NDArray[np.float64]], NDArray[np.float64]]]:
    """Residual and Jacobian functions of the correction (delta, tau) for MINPACK, and a
    lookup of the residuals at a point already evaluated.

    ``lmder`` asks for the Jacobian only at the point whose residuals it evaluated last, so
    both come from one ``projectPoints`` call (recomputed should that ever differ), and a
    repeated evaluation at the same point is answered from that call too. The two latest
    evaluations are kept: LM's answer is one of them (the last, or the one before a rejected
    trial step), so its residuals need no further projection.
    """
    last: list[Any] = [None, None, None]  # parameters (bytes), residuals, Jacobian
    before: list[Any] = [None, None, None]

    def residuals(x: NDArray[np.float64]) -> NDArray[np.float64]:
        key = x.tobytes()
        if key != last[0]:  # SciPy evaluates the start twice (a shape check, then lmder)
            projected, jacobian = cv2.projectPoints(points_cam, x[:3], x[3:], K, dist)
            before[0], before[1] = last[0], last[1]
            last[0], last[1], last[2] = key, projected.reshape(-1) - target_px, jacobian[:, :6]
        result: NDArray[np.float64] = last[1]
        return result

    def jacobian(x: NDArray[np.float64]) -> NDArray[np.float64]:
        if last[0] != x.tobytes():
            residuals(x)
        result: NDArray[np.float64] = last[2]
        return result

    def residuals_at(x: NDArray[np.float64]) -> NDArray[np.float64]:
        if before[0] == x.tobytes():
            result: NDArray[np.float64] = before[1]
            return result
        return residuals(x)

    return residuals, jacobian, residuals_at


def refine_fit(
    obj: NDArray[np.float64],
    img: NDArray[np.float64],
    K: NDArray[np.float64],
    dist: NDArray[np.float64],
    T_init: NDArray[np.float64],
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """LM from ``T_init`` on prepared arrays -> (T, residual vectors (N,2) px).

    The residuals are those LM last computed at its answer: a candidate pose costs no
    projection beyond LM's own; the Jacobian for the covariance is taken only for the pose
    that is kept (:func:`pose_reprojection`).
    """
    points_cam = obj @ T_init[:3, :3].T + T_init[:3, 3]
    fun, jac, residuals_at = _correction_problem(points_cam, img.reshape(-1), K, dist)
    x0 = np.zeros(6)
    if _LMDER is not None:
        x = _LMDER(fun, jac, x0, (), 0, 0, TOLERANCE, TOLERANCE, 0.0, MAX_EVALUATIONS,
                   _STEP_BOUND, None)[0]
    else:  # pragma: no cover - depends on the SciPy release
        x = leastsq(fun, x0, Dfun=jac, ftol=TOLERANCE, xtol=TOLERANCE,
                    maxfev=MAX_EVALUATIONS)[0]
    return left_corrected(T_init, x), residuals_at(x).reshape(-1, 2)


def left_corrected(T: NDArray[np.float64], x: NDArray[np.float64]) -> NDArray[np.float64]:
    """The pose T moved by the left correction x = (delta, tau): R(delta) (R P + t) + tau."""
    dR = cv2.Rodrigues(x[:3])[0]
    out: NDArray[np.float64] = np.empty((4, 4))
    out[:3, :3] = dR @ T[:3, :3]
    out[:3, 3] = dR @ T[:3, 3] + x[3:]
    out[3] = _BOTTOM_ROW
    return out


def pose_reprojection(
    obj: NDArray[np.float64],
    img: NDArray[np.float64],
    K: NDArray[np.float64],
    dist: NDArray[np.float64],
    T: NDArray[np.float64],
) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
    """(rotation vector (3,), residuals (N,2) px, Jacobian (2N,6) over the pose's own rotation
    vector and translation) of the pose ``T``: what the covariance is taken over."""
    rvec = np.asarray(cv2.Rodrigues(T[:3, :3])[0], dtype=np.float64).reshape(3)
    residuals, J = reprojection(obj, img, K, dist, rvec, T[:3, 3].copy())
    return rvec, residuals, J


def refine_arrays(
    obj: NDArray[np.float64],
    img: NDArray[np.float64],
    K: NDArray[np.float64],
    dist: NDArray[np.float64],
    T_init: NDArray[np.float64],
) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
    """LM from ``T_init`` on prepared arrays -> (T, residual vectors (N,2) px, Jacobian (2N,6)
    over the pose's own rotation vector and translation, for the covariance)."""
    T, _ = refine_fit(obj, img, K, dist, T_init)
    _, residuals, J = pose_reprojection(obj, img, K, dist, T)
    return T, residuals, J


def shift_pose(
    obj: NDArray[np.float64],
    img: NDArray[np.float64],
    K: NDArray[np.float64],
    dist: NDArray[np.float64],
    T: NDArray[np.float64],
) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
    """The least-squares pose for image points moved by a tiny amount, from the pose before.

    ``T`` minimises the reprojection error on image points a few hundredths of a pixel away
    from ``img``. To first order the minimum moves by -(J^T J)^-1 J^T r (r: the residuals
    against ``img``), the propagation of a point shift into the pose that the covariance also
    rests on, and what that neglects is second order in the shift. The step is taken in the
    same left correction as LM's (see the module docstring), where J is well conditioned for
    any pose. For the perspective-bias correction this lands within LM's own tolerance of the
    minimum a second LM run reaches (tested), for one 6x6 solve instead of a few projections.
    Returns (T, residuals (N,2), Jacobian (2N,6) over the pose's own rotation vector and
    translation) at the moved pose.
    """
    points_cam = obj @ T[:3, :3].T + T[:3, 3]
    zero = np.zeros(3)
    projected, jacobian = cv2.projectPoints(points_cam, zero, zero, K, dist)
    residuals = np.asarray(projected, dtype=np.float64).reshape(-1, 1) - img.reshape(-1, 1)
    ok, step = cv2.solve(np.asarray(jacobian[:, :6]), -residuals,
                         flags=cv2.DECOMP_CHOLESKY | cv2.DECOMP_NORMAL)
    # Not ok: J is rank-deficient (the points do not determine the pose), so T stays.
    moved = left_corrected(T, np.asarray(step, dtype=np.float64).reshape(6)) if ok else T
    _, residuals2, J2 = pose_reprojection(obj, img, K, dist, moved)
    return moved, residuals2, J2
