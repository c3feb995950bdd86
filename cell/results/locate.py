"""The locate answer: where the target is, the arm pose it was seen from, how well it fits."""

from __future__ import annotations

from cell.results.base import Result
from cell.results.consistency import Consistency
from cell.results.pose import Pose


class LocateQuality(Result):
    rms_px: float
    max_residual_px: float
    ambiguous: bool
    converged: bool
    n_points: int
    covariance: list[list[float]] | None
    frame_age_s: float
    n_frames: int
    spread_mm: float
    spread_deg: float


class LocateResult(Result):
    """Where the target is, in the base frame and the camera frame, and how well it fits;
    ``consistency`` judges one locate's residuals and frame spread (no motion to judge)."""

    T_base_target: Pose
    T_camera_target: Pose
    T_base_tcp: Pose  # at the frame's capture time
    quality: LocateQuality
    frame_sequence: int
    consistency: Consistency
