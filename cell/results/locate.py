"""The locate answers: where the target is, the arm pose it was seen from, how well it fits;
and every part in view (``LocateAllResult``)."""

from __future__ import annotations

from typing import Literal

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


PickOrder = Literal["nearest_to_camera_axis", "highest", "largest_x", "smallest_x"]
InstanceFlag = Literal["border", "overlap"]


class InstanceQuality(Result):
    """How well one part's pose fits: its reprojection, how its dot identities were decided
    (``identity``), and whether another pose fits as well (``ambiguous``)."""

    rms_px: float
    max_residual_px: float
    ambiguous: bool
    converged: bool
    identity: str
    n_points: int  # dots matched
    n_dots: int  # dots of the layout
    covariance: list[list[float]] | None


class LocatedInstance(Result):
    """One part in view. ``id`` stays the part's while it stays within ``[locate]
    same_part_mm`` of where it was seen last; ``flags``: ``border`` (a dot at or past the
    image border), ``overlap`` (dots hidden, foreign dots on it, or another part over it),
    each with a sentence in ``reasons``; ``pickable``: no flag."""

    id: int
    layout: str
    T_base_target: Pose
    T_camera_target: Pose
    centre_base_mm: tuple[float, float, float]  # of the layout's dots
    quality: InstanceQuality
    flags: list[InstanceFlag]
    reasons: list[str]
    pickable: bool


class UnresolvedDots(Result):
    """Dots that looked like one part and that no layout explains, where (px) and why."""

    n_dots: int
    box_px: tuple[float, float, float, float]  # x0, y0, x1, y1 of their centres
    flags: list[InstanceFlag]
    reason: str


class LocateAllResult(Result):
    """Every part of the looked-for layouts in one frame, in the order ``order`` gives
    (pickable parts first), and the dots nothing explains."""

    instances: list[LocatedInstance]
    unresolved: list[UnresolvedDots]
    order: PickOrder
    layouts: list[str]
    T_base_tcp: Pose  # at the frame's capture time
    frame_sequence: int
    frame_age_s: float
