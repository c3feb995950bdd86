"""Camera intrinsics from several images of a board (OpenCV's calibrateCamera).

The per-image reprojection errors matter as much as the overall rms: one blurred or mis-detected
image inflates the rms, and the per-image list says which one to drop.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import cv2
import numpy as np
from numpy.typing import NDArray

from estimator.bias import correct_image_points
from estimator.calib.board import Board, detect_board
from estimator.camera import CameraModel

# Fewer views than this leave focal length and principal point poorly separated.
MIN_VIEWS = 3


class IntrinsicsError(ValueError):
    """Not enough usable images (or inconsistent sizes) to calibrate."""

    code = "intrinsics_failed"


@dataclass(frozen=True)
class IntrinsicsResult:
    """The calibrated camera and how well it explains each image it was computed from."""

    camera: CameraModel
    rms_px: float
    per_image_rms_px: tuple[float, ...]  # in the order of ``used``
    used: tuple[int, ...]  # indices of the input images the board was found in
    rejected: tuple[int, ...]  # indices where it was not found
    T_camera_board: tuple[NDArray[np.float64], ...]  # board pose in each used image (mm)
    coverage: float = 0.0  # share of the image inside the hull of every detected point


# Distortion is only measured where the board was seen; beyond, the polynomial extrapolates
# (k2 above all). Below this share of the image the result says so: on the simulated cell a
# board covering 5 % left the corners 87 px off, one covering 37 % 0.15 px
# (docs/commissioning.md).
MIN_COVERAGE = 0.25


def coverage(image_points_px: Sequence[NDArray[np.float64]], image_size: tuple[int, int]
             ) -> float:
    """Share of the image (``(width, height)``) inside the convex hull of all the points."""
    pts = np.concatenate([np.asarray(p, dtype=np.float32).reshape(-1, 2)
                          for p in image_points_px])
    if len(pts) < 3:
        return 0.0
    hull = cv2.convexHull(pts)
    return float(cv2.contourArea(hull)) / float(image_size[0] * image_size[1])


def calibrate_from_points(
    board: Board,
    image_points_px: Sequence[NDArray[np.float64]],
    image_size: tuple[int, int],
    distortion: bool = True,
) -> tuple[CameraModel, float, list[float], list[NDArray[np.float64]]]:
    """Calibrate from already detected features; ``image_size`` is (width, height).

    With ``distortion`` False the lens is modelled as an ideal pinhole (all coefficients fixed
    at zero), which suits rendered images and rectified streams.
    """
    if len(image_points_px) < MIN_VIEWS:
        raise IntrinsicsError(
            f"the board was found in {len(image_points_px)} image(s); need at least {MIN_VIEWS} "
            "views at different tilts"
        )
    obj = board.object_points_mm().astype(np.float32)
    objs = [obj] * len(image_points_px)
    imgs = [np.asarray(p, dtype=np.float32).reshape(-1, 1, 2) for p in image_points_px]
    flags = cv2.CALIB_FIX_K3
    if not distortion:
        flags |= cv2.CALIB_FIX_K1 | cv2.CALIB_FIX_K2 | cv2.CALIB_ZERO_TANGENT_DIST
    w, h = image_size
    criteria = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_COUNT, 100, 1e-12)
    rms, K, dist, rvecs, tvecs = cv2.calibrateCamera(
        objs, imgs, (w, h), None, None, flags=flags, criteria=criteria
    )
    dist = np.asarray(dist, dtype=float).ravel()[:5]
    camera = CameraModel(
        float(K[0, 0]), float(K[1, 1]), float(K[0, 2]), float(K[1, 2]),
        tuple(dist) if distortion else (), w, h,
    )
    per_image, poses = [], []
    for img, rvec, tvec in zip(imgs, rvecs, tvecs, strict=True):
        proj, _ = cv2.projectPoints(obj, rvec, tvec, K, dist)
        err = np.linalg.norm(proj.reshape(-1, 2) - img.reshape(-1, 2), axis=1)
        per_image.append(float(np.sqrt(np.mean(err**2))))
        T = np.eye(4)
        T[:3, :3] = cv2.Rodrigues(rvec)[0]
        T[:3, 3] = np.asarray(tvec, dtype=float).ravel()
        poses.append(T)
    return camera, float(rms), per_image, poses


def calibrate_intrinsics(
    board: Board, images: Sequence[NDArray[np.uint8]], distortion: bool = True,
    dot_diameter_mm: float | None = None,
) -> IntrinsicsResult:
    """Detect the board in every image and calibrate from those where it was found.

    A circle grid's detected points are the dots' image centroids, which perspective moves off
    the images of the dots' centres (:mod:`estimator.bias`) by an amount that grows with the
    tilt, so the focal length comes out biased (0.03 % low measured with 14 mm dots at 35 mm
    pitch: 0.13 mm of distance at 450 mm). With the dots' ``dot_diameter_mm`` the points are
    corrected with the poses and lens of the previous solution and calibrated again, twice."""
    if not images:
        raise IntrinsicsError("no images given")
    sizes = {im.shape[:2] for im in images}
    if len(sizes) != 1:
        raise IntrinsicsError(f"images differ in size: {sorted(sizes)}")
    h, w = images[0].shape[:2]
    used, rejected, points = [], [], []
    for i, im in enumerate(images):
        pts = detect_board(board, im)
        if pts is None:
            rejected.append(i)
        else:
            used.append(i)
            points.append(pts)
    camera, rms, per_image, poses = calibrate_from_points(board, points, (w, h), distortion)
    if dot_diameter_mm is not None and board.kind != "chessboard":
        obj = board.object_points_mm()
        for _ in range(2):
            corrected = [correct_image_points(p, T, obj, dot_diameter_mm, camera)
                         for p, T in zip(points, poses, strict=True)]
            camera, rms, per_image, poses = calibrate_from_points(board, corrected, (w, h),
                                                                  distortion)
    return IntrinsicsResult(
        camera=camera, rms_px=rms, per_image_rms_px=tuple(per_image), used=tuple(used),
        rejected=tuple(rejected), T_camera_board=tuple(poses),
        coverage=coverage(points, (w, h)),
    )
