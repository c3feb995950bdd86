"""The hand-eye solution (every method's answer, the residuals, the verdict) and the answer of
applying one. ``T_flange_camera`` is ``T_base_camera`` for a fixed camera."""

from __future__ import annotations

from typing import Literal

from cell.results.base import Result
from cell.results.pose import Pose

# what a hand-eye result's transform is: the flange's camera, or a fixed camera in the base
MountTransform = Literal["T_flange_camera", "T_base_camera"]


class MethodResidual(Result):
    """ViSP's consistency residual: each view's ``T_base_board`` from their mean."""

    mean_mm: float
    mean_deg: float
    max_mm: float
    max_deg: float
    per_view_mm: list[float]
    per_view_deg: list[float]


class MethodSolution(Result):
    """One AX = XB solution."""

    T_flange_camera: Pose
    T_base_board: Pose
    residual: MethodResidual


class MeanResidual(Result):
    mean_mm: float
    mean_deg: float


class FreeIntrinsics(Result):
    """The joint fit with fx, fy, cx, cy let free: a lower rms blames the intrinsics."""

    rms_px: float
    fx: float
    fy: float
    cx: float
    cy: float


class RefinedSolution(Result):
    """A fit on every image point (joint: all free; hybrid: the motions' rotation held)."""

    T_flange_camera: Pose
    T_base_board: Pose
    rms_px: float
    per_view_rms_px: list[float]
    std_position_mm: list[float]
    converged: bool


class JointSolution(RefinedSolution):
    std_rotvec_deg: list[float]
    residual: MeanResidual | None = None
    free_intrinsics: FreeIntrinsics | None = None


class KinematicSolution(Result):
    """The mount fitted with the arm's geometry: the DH deltas against the nominal table."""

    T_flange_camera: Pose
    T_base_board: Pose
    rms_px: float
    per_view_rms_px: list[float]
    dh_delta_theta_rad: list[float]
    dh_delta_d_mm: list[float]
    dh_delta_a_mm: list[float]
    converged: bool


class ViewFit(Result):
    """A view used, with its board pose's own reprojection rms."""

    name: str
    pnp_rms_px: float


class CalibrationVerdict(Result):
    """``consistent`` False: the data disagree with themselves (``findings`` say where)."""

    consistent: bool
    findings: list[str]
    text: str


class HandEyeSolution(Result):
    """Everything a hand-eye solve reports; ``chosen`` names the method whose
    ``T_flange_camera`` is the answer."""

    chosen: str
    T_flange_camera: Pose
    methods: dict[str, MethodSolution]
    joint: JointSolution | None
    hybrid: RefinedSolution | None
    kinematic: KinematicSolution | None
    views: list[ViewFit]
    skipped_views: list[str]
    verdict: CalibrationVerdict


class MountFields(Result):
    """What a result's ``T_flange_camera`` is: a fixed camera's is ``T_base_camera``, also
    given under that name."""

    mount: Literal["hand", "fixed"]
    transform: MountTransform
    T_base_camera: Pose | None = None  # a fixed camera


class ConfigFileChange(Result):
    """What writing the config file changed, and where the old file is kept."""

    file: str
    backup: str
    old_T_flange_camera: Pose
    new_T_flange_camera: Pose
    distance_mm: float
    distance_deg: float
    key: MountTransform


class CalibrationApplied(MountFields):
    """The answer of applying a calibration job's mount."""

    job_id: str
    T_flange_camera: Pose
    running: bool
    written_config: str | None
    config_change: ConfigFileChange | None
