"""The POSIT seed pose for any model: general POSIT for a solid, coplanar POSIT for a plate.

The two variants share the model and the image normalisation (:mod:`estimator.posit`); this
module only chooses, so neither variant needs to know the other.
"""

from __future__ import annotations

from numpy.typing import ArrayLike

from estimator.camera import CameraModel
from estimator.coplanar import posit_coplanar
from estimator.errors import BehindCameraError
from estimator.posit import (
    PositResult,
    all_in_front,
    normalised_image_points,
    object_model,
    posit_general,
    reprojection_rms_px,
)


def posit(
    object_points_mm: ArrayLike,
    image_points_px: ArrayLike,
    camera: CameraModel,
    *,
    max_iterations: int = 100,
    tolerance_px: float = 1e-4,
) -> PositResult:
    """POSIT seed pose from matched points, no refinement (DeMenthon & Davis 1995).

    The first point is the reference point P0. Iteration stops when no perspective-corrected
    image point moves by more than ``tolerance_px`` (converted to normalised units with the mean
    focal length) or after ``max_iterations``. The final rotation is orthonormalised with an
    SVD, because POSIT's rows I/|I| and J/|J| are not exactly orthogonal. Planar models
    (singular object matrix) go to coplanar POSIT, which also returns the other branch.

    Raises TooFewBlobsError (< 4 points), DegenerateGeometryError (collinear model or image) and
    BehindCameraError (the best solution puts part of the target behind the camera).
    """
    model = object_model(object_points_mm)
    xy = normalised_image_points(image_points_px, camera, model.n_points)
    tolerance = tolerance_px / (0.5 * (camera.fx + camera.fy))
    if model.planar:
        return posit_coplanar(model, xy, image_points_px, camera, max_iterations, tolerance)
    T, iterations, converged = posit_general(model, xy, max_iterations, tolerance)
    if not all_in_front(T, model.points_mm):
        raise BehindCameraError(
            "POSIT put part of the target behind the camera: the image points probably do not "
            "match the model (check the correspondence)"
        )
    rms = reprojection_rms_px(T, model.points_mm, image_points_px, camera)
    return PositResult(T, iterations, converged, rms)
