"""The ``consistency`` block: does what the cell saw agree with itself
(:mod:`cell.vision.consistency` judges; here is what it reports)."""

from __future__ import annotations

from typing import Literal

from cell.results.base import Result


class Reprojection(Result):
    """Every averaged frame's reprojection rms against the limit (px)."""

    rms_px: list[float]
    max_rms_px: float
    limit_px: float


class FrameSpread(Result):
    """How far the frames averaged into one locate spread from their mean."""

    max_mm: float
    max_deg: float
    limit_mm: float
    limit_deg: float


class MotionCheck(Result):
    """Two locates of a target at rest from two arm poses: the arm's reported motion against
    the target's seen motion in the base frame."""

    between: tuple[str, str]
    arm_moved_mm: float
    arm_moved_deg: float
    target_moved_mm: float
    target_moved_deg: float
    judged: bool  # the arm moved enough for the pair to reveal a calibration error
    ok: bool


class MotionJudgement(Result):
    """The pairs of locates judged (none when the target is not at rest)."""

    target_at_rest: bool
    checks: list[MotionCheck]
    judged: int
    max_target_moved_mm: float | None
    max_target_moved_deg: float | None
    limit_mm: float
    limit_deg: float
    min_arm_motion_mm: float
    min_arm_motion_deg: float


class Consistency(Result):
    """The verdict on a result's evidence: ``codes`` are error codes
    (``reprojection_too_large``, ``spread_too_large``, ``calibration_inconsistent``), each with
    its finding in words."""

    verdict: Literal["consistent", "inconsistent", "unchecked"]
    codes: list[str]
    findings: list[str]
    reprojection: Reprojection
    frame_spread: FrameSpread
    motion: MotionJudgement
