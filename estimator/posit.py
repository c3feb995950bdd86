"""POSIT (DeMenthon & Davis 1995): the pose seed from one image of a known 3-D point set.

POSIT needs no initial guess, which is why it seeds the refinement: it approximates the
perspective image by a scaled orthographic one, solves that linearly with the *object matrix*
(the pseudo-inverse of the model's vectors from the reference point P0), and then corrects the
image points for the perspective it ignored (the epsilons) until they stop changing.

The object matrix depends only on the model, so :func:`object_model` computes it once per model
and caches it; each frame then costs a handful of small matrix products per iteration. Planar
models make that matrix singular and are handled by :mod:`estimator.coplanar`;
:func:`estimator.seed.posit` chooses between the two.

Everything runs in undistorted normalised image coordinates, so the focal length is 1.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numba
import numpy as np
from numpy.typing import ArrayLike, NDArray

from estimator.arrays import kernel_array
from estimator.camera import CameraModel
from estimator.errors import DegenerateGeometryError, TooFewBlobsError

MIN_POINTS = 4
PLANAR_RATIO = 1e-6  # smallest/largest singular value of the centred model below this: planar
COLLINEAR_RATIO = 1e-6  # second/largest singular value below this: collinear (model or image)
_CACHE_SIZE = 64


@dataclass(frozen=True)
class PositResult:
    """Raw POSIT output: the pose, how the iteration went, and for planar models the other branch.

    ``alternative`` is ``(T_camera_target, rms_px)`` of the losing coplanar branch, or None (for
    non-planar models, or when the other branch put the target behind the camera).
    """

    T_camera_target: NDArray[np.float64]  # 4x4, mm
    iterations: int
    converged: bool
    rms_px: float
    alternative: tuple[NDArray[np.float64], float] | None = None


class ObjectModel:
    """Per-model constants of POSIT, computed once: vectors P0Pi, object matrix, plane normal."""

    def __init__(self, points_mm: NDArray[np.float64]) -> None:
        if len(points_mm) < MIN_POINTS:
            raise TooFewBlobsError(len(points_mm), MIN_POINTS, "POSIT needs 4 model points")
        if not np.all(np.isfinite(points_mm)):
            raise ValueError("object points must be finite")
        self.points_mm = points_mm
        self.n_points = len(points_mm)
        # Vectors from the reference point P0 to every point (row 0 is zero), so that one matrix
        # product gives the depth offsets of all points at once.
        self.vectors_mm = points_mm - points_mm[0]
        self.tail_mm = self.vectors_mm[1:]  # P0Pi for i >= 1 (a contiguous row block)
        self.origin_mm = self.points_mm[0].copy()  # P0
        self.centre_mm = points_mm.mean(axis=0)
        s = np.linalg.svd(points_mm - points_mm.mean(axis=0), compute_uv=False)
        if s[0] <= 0.0 or s[1] <= COLLINEAR_RATIO * s[0]:
            raise DegenerateGeometryError(
                "the model points are collinear or coincident, so the pose is undetermined: "
                "use a target with at least 4 dots not on one line"
            )
        self.planar = bool(s[2] <= PLANAR_RATIO * s[0])
        A = self.vectors_mm[1:]
        # Object matrix B: pseudo-inverse of the (N-1)x3 matrix of P0Pi. For a planar model
        # the cut-off drops the (numerically zero) normal direction, which coplanar POSIT
        # then recovers from the orthonormality constraints.
        self.object_matrix = np.ascontiguousarray(np.linalg.pinv(A, rcond=PLANAR_RATIO * 10))
        _, _, vt = np.linalg.svd(A)
        self.normal = vt[2].copy()  # unit normal of the model plane (only meaningful if planar)
        self.normal_tuple = (float(vt[2, 0]), float(vt[2, 1]), float(vt[2, 2]))


_MODELS: dict[bytes, ObjectModel] = {}


def object_model(object_points_mm: ArrayLike) -> ObjectModel:
    """The cached :class:`ObjectModel` of these points (keyed by their exact values)."""
    pts = np.ascontiguousarray(object_points_mm, dtype=float)
    if pts.ndim != 2 or pts.shape[1] != 3:
        raise ValueError(f"object points must have shape (N, 3), got {pts.shape}")
    key = pts.tobytes()
    model = _MODELS.get(key)
    if model is None:
        model = ObjectModel(pts.copy())
        if len(_MODELS) >= _CACHE_SIZE:
            _MODELS.pop(next(iter(_MODELS)))
        _MODELS[key] = model
    return model


def normalised_image_points(
    image_points_px: ArrayLike, camera: CameraModel, n_expected: int
) -> NDArray[np.float64]:
    """Undistorted normalised coordinates of the image points, after validating them."""
    img = np.asarray(image_points_px, dtype=float)
    if img.ndim != 2 or img.shape[1] != 2:
        raise ValueError(f"image points must have shape (N, 2), got {img.shape}")
    if len(img) != n_expected:
        raise ValueError(f"{len(img)} image points for {n_expected} object points")
    if camera.has_distortion:
        if not np.isfinite(img).all():
            raise ValueError("image points must be finite")
        xy = kernel_array(camera.undistort_points(img))
    else:  # the pinhole inverse, compiled with the spread below: this runs every frame
        xy = _pinhole_normalised(kernel_array(img), camera.fx, camera.fy, camera.cx, camera.cy)
    spread = _spread_ratio(xy)
    if not spread >= 0.0:  # NaN: a coordinate is not finite
        raise ValueError("image points must be finite")
    if spread <= COLLINEAR_RATIO**2:
        raise DegenerateGeometryError(
            "the image points are collinear or coincident (target seen edge-on?): tilt the "
            "target towards the camera"
        )
    return xy


@numba.njit(cache=True, nogil=True)
def _pinhole_normalised(
    img: NDArray[np.float64], fx: float, fy: float, cx: float, cy: float
) -> NDArray[np.float64]:
    """Pixel -> normalised coordinates of a camera without distortion."""
    out = np.empty_like(img)
    for i in range(img.shape[0]):
        out[i, 0] = (img[i, 0] - cx) / fx
        out[i, 1] = (img[i, 1] - cy) / fy
    return out


@numba.njit(cache=True, nogil=True)
def _spread_ratio(xy: NDArray[np.float64]) -> float:
    """lambda_min / lambda_max of the points' 2x2 scatter matrix (the squared ratio of their
    singular values, closed form, no SVD): 0 for collinear or coincident points, NaN when a
    coordinate is not finite."""
    n = xy.shape[0]
    mx = my = 0.0
    for i in range(n):
        mx += xy[i, 0]
        my += xy[i, 1]
    mx /= n
    my /= n
    a = b = d = 0.0
    for i in range(n):
        dx, dy = xy[i, 0] - mx, xy[i, 1] - my
        a += dx * dx
        b += dx * dy
        d += dy * dy
    if not (math.isfinite(a) and math.isfinite(b) and math.isfinite(d)):
        return math.nan
    half_trace, det = 0.5 * (a + d), a * d - b * b
    lam_max = half_trace + math.sqrt(max(half_trace * half_trace - det, 0.0))
    if lam_max <= 0.0:
        return 0.0
    return max(det / lam_max, 0.0) / lam_max


def pose_from_rows(
    R_rows: NDArray[np.float64], scale: float, xy0: NDArray[np.float64], P0: NDArray[np.float64],
) -> NDArray[np.float64]:
    """4x4 T_camera_target from POSIT's (I/|I|, J/|J|, R1xR2) rows, the scale and P0's image.

    The rows of plain POSIT are only approximately orthonormal (I and J come from a
    least-squares solve), so the rotation is projected onto SO(3) with an SVD. P0 sits at
    depth Tz = 1/s on its image ray. (Coplanar POSIT's rows are orthonormal by construction;
    its compiled kernel composes its poses itself.)
    """
    U, _, Vt = np.linalg.svd(R_rows)
    R = U @ Vt
    if np.linalg.det(R) < 0:
        R = U @ np.diag([1.0, 1.0, -1.0]) @ Vt
    Tz = 1.0 / scale
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = np.array([xy0[0] * Tz, xy0[1] * Tz, Tz]) - R @ P0
    return T


def reprojection_rms_px(
    T: NDArray[np.float64], points_mm: NDArray[np.float64], image_points_px: ArrayLike,
    camera: CameraModel,
) -> float:
    """Root-mean-square pixel distance between the points' projections and the image points."""
    img = np.asarray(image_points_px, dtype=float)
    if not camera.has_distortion:  # compiled: this runs several times per frame
        return _pinhole_rms_px(kernel_array(T), kernel_array(points_mm),
                               kernel_array(img.reshape(-1, 2)),
                               camera.fx, camera.fy, camera.cx, camera.cy)
    P = points_mm @ T[:3, :3].T + T[:3, 3]
    if P[:, 2].min() <= 0.0:
        return math.inf
    d = camera.project(P) - img
    return math.sqrt(float(np.vdot(d, d)) / len(d))


@numba.njit(cache=True, nogil=True)
def _pinhole_rms_px(
    T: NDArray[np.float64], P: NDArray[np.float64], img: NDArray[np.float64],
    fx: float, fy: float, cx: float, cy: float,
) -> float:
    """:func:`reprojection_rms_px` of a camera without distortion (inf if a point is behind)."""
    total = 0.0
    for i in range(P.shape[0]):
        x = T[0, 0] * P[i, 0] + T[0, 1] * P[i, 1] + T[0, 2] * P[i, 2] + T[0, 3]
        y = T[1, 0] * P[i, 0] + T[1, 1] * P[i, 1] + T[1, 2] * P[i, 2] + T[1, 3]
        z = T[2, 0] * P[i, 0] + T[2, 1] * P[i, 1] + T[2, 2] * P[i, 2] + T[2, 3]
        if z <= 0.0:
            return math.inf
        du, dv = fx * x / z + cx - img[i, 0], fy * y / z + cy - img[i, 1]
        total += du * du + dv * dv
    return math.sqrt(total / P.shape[0])


def all_in_front(T: NDArray[np.float64], points_mm: NDArray[np.float64]) -> bool:
    """True when every model point has positive depth in the camera frame."""
    return min((points_mm @ T[2, :3]).tolist()) > -T[2, 3]


class FrameSystem:
    """Per-frame constants of the POSIT linear system, so each iteration is two small products.

    With corrected image points x_i(1 + eps_i) - x0, the scaled-orthographic solution is
    I = B (x - x0) + (B diag(x)) eps, and likewise for J; both are stacked into one 6-vector
    ``offset + gain @ eps``. (Coplanar POSIT builds the same system inside its compiled
    kernel, :func:`estimator.coplanar._branches`.)
    """

    def __init__(self, model: ObjectModel, xy: NDArray[np.float64]) -> None:
        B = model.object_matrix
        pts = xy[1:]
        x0, y0 = float(xy[0, 0]), float(xy[0, 1])
        self.offset = np.concatenate((B @ (pts[:, 0] - x0), B @ (pts[:, 1] - y0)))
        self.gain = np.vstack((B * pts[:, 0], B * pts[:, 1]))
        # How far (normalised units) a corrected point moves per unit change of its epsilon.
        self.radius = np.sqrt((pts * pts).sum(axis=1))


Vec3 = tuple[float, float, float]


def unit_rows(I: Vec3, J: Vec3) -> tuple[Vec3, Vec3, Vec3, float] | None:
    """POSIT's rows R1 = I/|I|, R2 = J/|J|, R3 = R1 x R2 and the scale s = sqrt(|I||J|).

    Scalar arithmetic on purpose: for 3-vectors it is several times faster than numpy calls.
    None when I or J vanishes.
    """
    nI = math.sqrt(I[0] * I[0] + I[1] * I[1] + I[2] * I[2])
    nJ = math.sqrt(J[0] * J[0] + J[1] * J[1] + J[2] * J[2])
    if nI == 0.0 or nJ == 0.0:
        return None
    a0, a1, a2 = I[0] / nI, I[1] / nI, I[2] / nI
    b0, b1, b2 = J[0] / nJ, J[1] / nJ, J[2] / nJ
    r3 = (a1 * b2 - a2 * b1, a2 * b0 - a0 * b2, a0 * b1 - a1 * b0)
    return (a0, a1, a2), (b0, b1, b2), r3, math.sqrt(nI * nJ)


def posit_general(
    model: ObjectModel, xy: NDArray[np.float64], max_iterations: int, tolerance: float
) -> tuple[NDArray[np.float64], int, bool]:
    """The POSIT iteration for a non-planar model on normalised points -> (T, iterations, ok).

    ``tolerance`` is in normalised units: iteration stops when no perspective-corrected image
    point x_i(1 + eps_i) moves by more than it. One iteration is a (6,N-1) matrix-vector
    product for I and J, scalar arithmetic for the rows, and a (N-1,3) product for the new
    epsilons; everything per frame is prepared once in :class:`FrameSystem`.
    """
    system = FrameSystem(model, xy)
    V = model.vectors_mm[1:]
    offset, gain, radius = system.offset, system.gain, system.radius
    eps = np.zeros(len(V))
    rows: tuple[Vec3, Vec3, Vec3, float] | None = None
    converged = False
    iterations = 0
    for iterations in range(1, max_iterations + 1):  # noqa: B007 - reported after the loop
        i0, i1, i2, j0, j1, j2 = (offset + gain @ eps).tolist()
        rows = unit_rows((i0, i1, i2), (j0, j1, j2))
        if rows is None:
            raise DegenerateGeometryError("POSIT found no scaled-orthographic solution")
        r3, scale = rows[2], rows[3]
        # eps_i = (P0Pi . R3) / Tz with Tz = f/s, f = 1
        new_eps = V @ np.array((r3[0] * scale, r3[1] * scale, r3[2] * scale))
        step = float((np.abs(new_eps - eps) * radius).max())
        eps = new_eps
        if step < tolerance:
            converged = True
            break
    assert rows is not None  # max_iterations >= 1
    T = pose_from_rows(np.array(rows[:3]), rows[3], xy[0], model.points_mm[0])
    return T, iterations, converged
