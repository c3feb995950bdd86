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
class AmbiguityTest:
    """How the best alternative pose compares with the chosen one (see
    :mod:`estimator.ambiguity`): ``ambiguous`` only when it is a different pose at the dots
    (beyond the configured mm / deg) and not separable at the measured noise level."""

    ambiguous: bool
    different: bool  # the alternative moves a dot by > max_dot_mm or rotates by > max_deg
    dot_shift_mm: float  # largest displacement of a dot between the two poses
    rotation_deg: float
    delta_chi2: float  # (SSR_alt - SSR_best) / sigma^2
    threshold: float  # delta_chi2 above this: separable
    sigma_px: float  # the noise level used (measured, with a floor)
    margin: float  # delta_chi2 / threshold: below 1 the two are not separable
    test: str

    def as_dict(self) -> dict[str, Any]:
        return {k: (v if isinstance(v, (bool, str)) else float(v))
                for k, v in self.__dict__.items()}


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
    ambiguity: AmbiguityTest | None = None  # the test behind ``ambiguous`` (planar targets)
    # Poses that explain the same blobs exactly as well under a symmetry of the dot layout
    # (each with its own dot labels); filled by a full search on a symmetric target.
    equivalent_poses: tuple[AlternativePose, ...] = ()
    # How the dot identities were decided: "unique" (one matching fits), "symmetry" (a
    # symmetric layout: one of the equivalent labellings, by a fixed rule), "continuity"
    # (kept from the previous frames' pose), "ambiguous" (different matchings fit as well),
    # "given" (the caller matched the points).
    identity: str = "given"

    @property
    def ambiguity_margin(self) -> float | None:
        """delta_chi2 / threshold of the ambiguity test (None without an alternative)."""
        return None if self.ambiguity is None else self.ambiguity.margin

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
            "identity": self.identity,
            "ambiguity": None if self.ambiguity is None else self.ambiguity.as_dict(),
            "equivalent_poses": [
                {"T_camera_target": pose_dict(e.T_camera_target), "rms_px": float(e.rms_px)}
                for e in self.equivalent_poses],
        }
        if self.alternative is not None:
            out["alternative"] = {
                "T_camera_target": pose_dict(self.alternative.T_camera_target),
                "rms_px": float(self.alternative.rms_px),
            }
        return out
