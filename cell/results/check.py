"""What the calibration reference and its check return.

The reference is a dot plate fixed in the cell, seen from a few arm poses right after a
calibration; the check revisits those poses and sees the plate again. With the same joints,
the arm's own kinematic error repeats and cancels; what is left is what changed in the chain
from the flange to the plate's image: the camera's mount (a knock), the lens (a refocus), the
plate itself (moved).

``tcp_error_mm`` / ``tcp_error_deg`` say what the change means at the tool: how far an approach
to the reference at the configured standoff would now miss. A camera that changed (``cause``
``camera``) shifts the plate's image alike in every view's camera frame, and the approach
closes on views from its goal, so the change is carried there; a plate that moved shifts alike
in the base frame (``cause`` ``reference``: record the reference again if it was moved on
purpose). The verdict compares those with
``[check] tolerance_mm`` and ``tolerance_deg``.
"""

from __future__ import annotations

from typing import Literal

from cell.results.base import Result
from cell.results.pose import Pose

CheckVerdict = Literal["ok", "drifted"]
# what explains the views better: the camera changed (mount, lens), or the reference plate moved
CheckCause = Literal["camera", "reference"]


class ReferenceView(Result):
    """One view of the reference: where the arm stood and where the plate appeared."""

    view: int
    joints_deg: list[float]
    T_base_tcp: Pose
    T_base_reference: Pose
    rms_px: float


class ReferenceResult(Result):
    """A recorded reference: its views, the plate's mean pose and how the views agree."""

    views: list[ReferenceView]
    T_base_reference: Pose
    spread_mm: float
    spread_deg: float
    failed_views: list[str]


class CheckedView(Result):
    """One view of a check against the same view at recording: the plate's apparent shift
    in the base frame."""

    view: int
    shift_mm: tuple[float, float, float]
    distance_mm: float
    rotation_deg: float
    rms_px: float


class CheckResult(Result):
    verdict: CheckVerdict
    cause: CheckCause
    tcp_error_mm: float
    tcp_error_deg: float
    position_error_mm: float  # the reference's mean apparent shift
    rotation_error_deg: float
    spread_mm: float  # the cause's model: its largest miss of one view's plate pose
    spread_deg: float
    tolerance_mm: float
    tolerance_deg: float
    standoff_mm: float
    views: list[CheckedView]
    reference_recorded_at: float
    took_s: float
