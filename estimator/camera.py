"""Pinhole camera with OpenCV's distortion model.

Pixel <-> normalised coordinates go through OpenCV so the distortion model is exactly the one
the calibration produced (5, 8, 12 or 14 coefficients; an empty tuple means no distortion).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field

import cv2
import numpy as np
from numpy.typing import ArrayLike, NDArray


@dataclass(frozen=True)
class CameraModel:
    """Intrinsics of one image stream: focal lengths and principal point in px, distortion."""

    fx: float
    fy: float
    cx: float
    cy: float
    dist: Sequence[float] = field(default_factory=tuple)
    width: int = 1280
    height: int = 800

    def __post_init__(self) -> None:
        if not (self.fx > 0 and self.fy > 0):
            raise ValueError(f"focal lengths must be positive, got fx={self.fx}, fy={self.fy}")
        if self.width <= 0 or self.height <= 0:
            raise ValueError(f"image size must be positive, got {self.width}x{self.height}")
        n = len(self.dist)
        if n not in (0, 4, 5, 8, 12, 14):
            raise ValueError(f"dist must have 0, 4, 5, 8, 12 or 14 coefficients, got {n}")
        object.__setattr__(self, "dist", tuple(float(d) for d in self.dist))

    @property
    def K(self) -> NDArray[np.float64]:
        """3x3 intrinsic matrix."""
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])

    @property
    def dist_coeffs(self) -> NDArray[np.float64]:
        """Distortion as the array OpenCV expects (zeros(5) when there is none)."""
        return np.asarray(self.dist, dtype=float) if self.dist else np.zeros(5)

    @property
    def has_distortion(self) -> bool:
        return any(d != 0.0 for d in self.dist)

    def undistort_points(self, points_px: ArrayLike) -> NDArray[np.float64]:
        """Pixel coordinates (N,2) -> normalised image coordinates (N,2), distortion removed."""
        pts = np.asarray(points_px, dtype=float).reshape(-1, 2)
        if not self.has_distortion:
            x = (pts[:, 0] - self.cx) / self.fx
            return np.column_stack((x, (pts[:, 1] - self.cy) / self.fy))
        out = cv2.undistortPoints(pts.reshape(-1, 1, 2), self.K, self.dist_coeffs)
        return np.asarray(out, dtype=float).reshape(-1, 2)

    def distort_points(self, normalized: ArrayLike) -> NDArray[np.float64]:
        """Normalised image coordinates (N,2) -> pixel coordinates (N,2), distortion applied."""
        xy = np.asarray(normalized, dtype=float).reshape(-1, 2)
        if not self.has_distortion:
            return np.column_stack((xy[:, 0] * self.fx + self.cx, xy[:, 1] * self.fy + self.cy))
        pts3 = np.column_stack((xy, np.ones(len(xy))))
        out, _ = cv2.projectPoints(pts3, np.zeros(3), np.zeros(3), self.K, self.dist_coeffs)
        return np.asarray(out, dtype=float).reshape(-1, 2)

    def project(self, points_camera_mm: ArrayLike) -> NDArray[np.float64]:
        """Project 3-D points given in the camera frame (N,3, z forward) to pixels (N,2)."""
        P = np.asarray(points_camera_mm, dtype=float).reshape(-1, 3)
        return self.distort_points(P[:, :2] / P[:, 2:3])

    def scaled(self, width: int, height: int) -> CameraModel:
        """The same lens seen at another resolution (binning/scaling, same field of view)."""
        sx, sy = width / self.width, height / self.height
        return CameraModel(
            self.fx * sx, self.fy * sy, (self.cx + 0.5) * sx - 0.5, (self.cy + 0.5) * sy - 0.5,
            self.dist, width, height,
        )
