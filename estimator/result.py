"""Result types shared by the detector, the solvers and the pipeline."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray

from estimator.transforms import pose_dict


@dataclass(frozen=True)
class Blob:
    """One detected dot: grey-level-weighted centre of gravity and its shape descriptors."""

    u: float
    v: float
    area: float  # px^2 of the thresholded region
    circularity: float  # 4*pi*area/perimeter^2, 1 for a disc
    inertia_ratio: float  # minor/major second-moment axis, 1 for a disc
    fill_ratio: float  # area / convex hull area
    major_axis_px: float = 0.0
    minor_axis_px: float = 0.0
    angle_rad: float = 0.0  # of the major axis, image x towards y
    ellipse_error: float = 0.0  # misfit of the outline to the moment ellipse (regions.py)

    def as_dict(self) -> dict[str, float]:
        return {
            "u": self.u, "v": self.v, "area": self.area, "circularity": self.circularity,
            "inertia_ratio": self.inertia_ratio, "fill_ratio": self.fill_ratio,
            "ellipse_error": self.ellipse_error,
        }


@dataclass(frozen=True)
class AlternativePose:
    """The losing branch of an ambiguous (e.g. coplanar) solution, kept for the caller to judge."""

    T_camera_target: NDArray[np.float64]
    rms_px: float


@dataclass(frozen=True)
class PoseResult:
    """A target pose in the camera frame with everything needed to judge it."""

    T_camera_target: NDArray[np.float64]  # 4x4, mm
    rms_px: float
    residuals_px: NDArray[np.float64]  # per-point reprojection error (N,)
    iterations: int  # of the seed (POSIT / coplanar POSIT) iteration
    converged: bool
    ambiguous: bool = False
    alternative: AlternativePose | None = None
    covariance: NDArray[np.float64] | None = None  # 6x6 over (rotvec rad, translation mm)
    matched_blobs: tuple[Blob, ...] = ()
    matched_ids: tuple[int, ...] = ()  # model dot index of each matched blob
    image_points_px: NDArray[np.float64] | None = None  # the points the pose was solved from
    notes: tuple[str, ...] = field(default_factory=tuple)

    def as_dict(self) -> dict[str, Any]:
        """JSON form: the pose object plus quality fields."""
        out: dict[str, Any] = {
            "T_camera_target": pose_dict(self.T_camera_target),
            "rms_px": float(self.rms_px),
            "residuals_px": [float(r) for r in self.residuals_px],
            "iterations": int(self.iterations),
            "converged": bool(self.converged),
            "ambiguous": bool(self.ambiguous),
            "alternative": None,
            "covariance": None if self.covariance is None else self.covariance.tolist(),
            "matched_ids": list(self.matched_ids),
            "blobs": [b.as_dict() for b in self.matched_blobs],
        }
        if self.alternative is not None:
            out["alternative"] = {
                "T_camera_target": pose_dict(self.alternative.T_camera_target),
                "rms_px": float(self.alternative.rms_px),
            }
        return out
