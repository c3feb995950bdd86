"""What a finished approach returns: one model per mode, discriminated by ``mode``.

Every approach says where the target was, where the arm went and how far it estimates it
is from the goal, how it estimated that (``estimated_error_basis``) and whether its evidence
agrees with itself (``consistency``). The rest is the mode's own: look-and-move's cycles,
the servo's and IBVS's loop figures.
"""

from __future__ import annotations

from typing import Annotated, Literal

from pydantic import Field

from cell.results.base import Result
from cell.results.consistency import Consistency
from cell.results.loop import FixedCameraView, IbvsLoop, ServoLoop
from cell.results.modes import ApproachMode
from cell.results.pose import Pose


class Cycle(Result):
    """One look-and-move cycle: the goal's correction from a locate at rest."""

    cycle: int
    correction_mm: float
    correction_deg: float
    rms_px: float
    spread_mm: float


class ClosingCorrection(Result):
    """A closing step at the goal that saw the target: the goal's correction."""

    step: int
    correction_mm: float
    correction_deg: float
    rms_px: float


class ClosingNotSeen(Result):
    """A closing step at the goal that did not see the target (why, in words); the goal
    before it stands."""

    step: int
    not_seen: str


ClosingStep = ClosingCorrection | ClosingNotSeen


class ErrorBasis(Result):
    """How an approach estimated its own error and what that estimate cannot see; ``frame``:
    the frame the estimate is measured in."""

    frame: Literal["base", "camera", "image"]
    text: str


class ApproachBase(Result):
    """What every approach reports."""

    converged: bool
    reached_T_base_tcp: Pose
    estimated_error_mm: float
    estimated_error_deg: float
    estimated_error_basis: ErrorBasis
    consistency: Consistency
    first_locate_s: float | None = Field(
        description="the seconds the locate before the first motion took (null: an earlier "
        "locate was used)")


class LookAndMoveApproach(ApproachBase, FixedCameraView):
    """Observe, locate, correct until the correction is under the tolerance, then move to the
    goal and close on still views there (a camera on the hand; a fixed camera corrects at the
    goal while it sees the target)."""

    mode: Literal[ApproachMode.look_and_move]
    cycles: list[Cycle]
    closing: list[ClosingStep] | None = None  # a camera on the hand
    T_base_target: Pose
    goal_T_base_tcp: Pose
    reach_error_mm: float
    reach_error_deg: float


class ServoApproach(ApproachBase, ServoLoop):
    """Position-based servoing on every frame until converged (an approach: on the mean of
    the target's poses at rest)."""

    mode: Literal[ApproachMode.servo]
    time_to_converge_s: float | None
    start_pose_source: Literal["last_seen"] | None = None  # a fixed camera hidden at the start


class IbvsApproach(ApproachBase, IbvsLoop):
    """Image-based servoing to a taught view until converged, then the settle steps."""

    mode: Literal[ApproachMode.ibvs]
    time_to_converge_s: float | None
    settle_steps_mm_deg: list[tuple[float, float]] | None = None  # each step's size
    # each step's frames averaged: of the still arm, and the loop's last ones carried to it
    settle_frames_still_carried: list[tuple[int, int]] | None = None


AnyApproach = LookAndMoveApproach | ServoApproach | IbvsApproach
ApproachResult = Annotated[AnyApproach, Field(discriminator="mode")]
