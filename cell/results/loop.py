"""What a closed loop (servo or IBVS, approaching or tracking) reports of its run: frame
counts, the error history, timing, and a fixed camera's occlusion of the target."""

from __future__ import annotations

from typing import Literal

from cell.results.base import Result
from cell.results.pose import Pose, Vec3
from cell.results.stats import LatencyStats, Percentiles


class ServoErrorRow(Result):
    """One point of a pose-based loop's error history (downsampled)."""

    t_s: float
    error_mm: float
    error_deg: float


class IbvsErrorRow(Result):
    """One point of an image-based loop's error history (downsampled)."""

    t_s: float
    image_error_px: float
    error_mm: float
    error_deg: float


class FixedCameraView(Result):
    """A fixed camera's account of the target's pose: the arm may hide the target near the
    goal, and the goal then comes from the last pose seen. Set only with a fixed camera."""

    camera_mount: Literal["fixed"] | None = None
    pose_source: Literal["live", "last_seen"] | None = None
    occluded: bool | None = None
    occluded_at_goal: bool | None = None
    pose_age_s: float | None = None  # of the pose held, when it was held
    occlusion_reason: str | None = None


class ServoLoop(FixedCameraView):
    """The pose-based loop's figures (:mod:`cell.servoing.position`)."""

    frames: int
    failed_frames: int
    stale_frames: int
    gated_frames: int
    T_base_target: Pose
    goal_T_base_tcp: Pose
    reached_T_base_tcp: Pose
    estimated_error_mm: float
    estimated_error_deg: float
    reach_error_mm: float
    reach_error_deg: float
    error_history: list[ServoErrorRow]
    pose_interval_ms: LatencyStats | None
    pose_latency_ms: LatencyStats | None
    target_velocity_mm_s: Vec3
    occlusions: int | None = None  # a fixed camera: times the last pose seen was held
    # an approach's target at rest: the goal came from the mean of this many poses, and the
    # estimated error adds twice the mean's standard error (cell.servoing.rest_mean)
    goal_frames_averaged: int | None = None
    # what the pose estimate resolves at the TCP (a hand camera; cell.servoing.view_bound),
    # included in the estimated error
    resolution_mm: float | None = None
    resolution_deg: float | None = None


class IbvsPhases(Result):
    """When each phase of an IBVS run began, in seconds from the loop's start; a phase the
    run did not reach is absent."""

    first_view: float | None = None
    first_frame_within: float | None = None
    window_image_within: float | None = None
    window_view_within: float | None = None
    window_still: float | None = None
    converged: float | None = None
    stopped: float | None = None
    settled: float | None = None
    frame_thread_join: float | None = None


class IbvsLoop(Result):
    """The image-based loop's figures (:mod:`cell.servoing.image`); the pose figures are the
    estimate's, the law never uses them."""

    frames: int
    failed_frames: int
    stale_frames: int
    frames_with_too_few_dots: int
    frames_missing_dots: int
    min_dots_used: int
    dots_taught: int
    min_dot_border_px: float | None
    interaction: Literal["current", "desired", "mean"]
    image_error_px_rms: float
    image_error_px_max: float
    estimated_error_mm: float
    estimated_error_deg: float
    reached_T_base_tcp: Pose
    pose_latency_ms: LatencyStats | None
    error_history: list[IbvsErrorRow]
    T_base_target: Pose | None = None  # of the newest view (absent: no view came)
    goal_T_base_tcp: Pose | None = None
    view_error_mm: float  # the TCP motion the converged window's mean view still asks for
    view_error_deg: float
    # what the window and the taught view resolve at the TCP (cell.servoing.view_bound): the
    # estimated error is the view error plus this
    resolution_mm: float | None = None
    resolution_deg: float | None = None
    phases_s: IbvsPhases
    gain_cap_per_s: Percentiles | None
