"""What a finished hand-eye routine job returns: the solution, the views that failed, how far
the result is from the mount in use, and where its views were saved."""

from __future__ import annotations

from cell.results.base import Result
from cell.results.calibration import HandEyeSolution, MountFields
from cell.results.pose import Pose


class FailedView(Result):
    view: int
    reason: str


class MountChange(Result):
    """The mount in use (under the result's ``transform`` name) and the result's distance
    from it."""

    T_flange_camera: Pose | None = None  # a camera on the hand
    T_base_camera: Pose | None = None  # a fixed camera
    distance_mm: float
    distance_deg: float


class SavedViews(Result):
    """Where the routine's views were saved as a dataset, or why not."""

    folder: str
    saved: bool
    views: int | None = None  # saved
    error: str | None = None  # not saved


class HandEyeRoutineResult(HandEyeSolution, MountFields):
    failed_views: list[FailedView]
    change_from_current: MountChange
    applied: None  # the job applies nothing: apply answers separately
    dataset: SavedViews | None  # null: [api] calibration_dir is not set
