"""The hand-eye report: every method's answer, the residuals ViSP reports, and a verdict.

The verdict exists because calibration data can be self-contradictory while every number still
looks plausible. It compares three things a person can act on: how well each image alone fits
its board pose (intrinsics and detection), how well one ``T_flange_camera`` explains all images
together (robot poses vs images), and whether the methods agree with each other.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from cell.results.calibration import (
    CalibrationVerdict,
    FreeIntrinsics,
    HandEyeSolution,
    JointSolution,
    KinematicSolution,
    MeanResidual,
    MethodResidual,
    MethodSolution,
    MountFields,
    RefinedSolution,
    ViewFit,
)
from cell.results.pose import Pose
from estimator.calib.handeye import BoardSpread, JointResult
from estimator.calib.kinematic import KinematicResult
from estimator.transforms import pose_dict, pose_distance

# An image whose own board pose leaves more than this is not explained by the intrinsics.
PNP_RMS_LIMIT_PX = 1.0
# The joint fit is "consistent" when it is within this of what the images allow on their own.
JOINT_RMS_LIMIT_PX = 0.5
JOINT_RMS_FACTOR = 2.0
# Closed-form methods that disagree by more than this signal weak or noisy motions.
METHOD_SPREAD_LIMIT_MM = 2.0
METHOD_SPREAD_LIMIT_DEG = 0.2
# Freeing the intrinsics must cut the joint rms by this factor to blame the intrinsics.
INTRINSICS_BLAME_FACTOR = 0.5
# The kinematic fit is chosen when it cuts the joint rms by this factor (and fits).
KINEMATIC_BLAME_FACTOR = 0.5
# The ``auto`` method trusts the free joint fit while its rms stays within this factor of the
# median view's own rms, or under the floor (exact poses: 1.7-1.8 on the simulated cell's six
# dots; the simulated arm reporting with UR's nominal table: 32-62), and takes the hybrid beyond.
AUTO_JOINT_RMS_FACTOR = 4.0
AUTO_JOINT_RMS_FLOOR_PX = 0.05


def joint_is_trusted(joint_rms_px: float, pnp_rms_px: NDArray[np.float64] | tuple[float, ...]
                     ) -> bool:
    """Whether the free joint fit leaves no more than the images' own noise (``auto``)."""
    median = float(np.median(np.asarray(pnp_rms_px, dtype=float)))
    return joint_rms_px <= max(AUTO_JOINT_RMS_FACTOR * median, AUTO_JOINT_RMS_FLOOR_PX)


@dataclass(frozen=True)
class MethodResult:
    """One AX = XB solution and ViSP's consistency residual for it."""

    method: str
    T_flange_camera: NDArray[np.float64]
    spread: BoardSpread

    def solution(self) -> MethodSolution:
        return MethodSolution(
            T_flange_camera=Pose.from_T(self.T_flange_camera),
            T_base_board=Pose.from_T(self.spread.T_base_board_mean),
            residual=MethodResidual(
                mean_mm=self.spread.mean_mm, mean_deg=self.spread.mean_deg,
                max_mm=float(self.spread.per_view_mm.max()),
                max_deg=float(self.spread.per_view_deg.max()),
                per_view_mm=[float(v) for v in self.spread.per_view_mm],
                per_view_deg=[float(v) for v in self.spread.per_view_deg]))


@dataclass(frozen=True)
class Verdict:
    consistent: bool
    findings: tuple[str, ...]

    @property
    def text(self) -> str:
        head = ("The data agree with themselves." if self.consistent
                else "The data disagree with themselves.")
        return " ".join((head, *self.findings))


@dataclass(frozen=True)
class HandEyeReport:
    """Everything ``cell calibrate hand-eye`` prints; ``chosen`` names the result to use."""

    view_names: tuple[str, ...]
    skipped_views: tuple[str, ...]  # board not found
    pnp_rms_px: tuple[float, ...]  # per used view: its board pose alone
    methods: dict[str, MethodResult]
    joint: JointResult | None
    joint_spread: BoardSpread | None
    joint_free_intrinsics: JointResult | None
    chosen: str
    verdict: Verdict
    hybrid: JointResult | None = None  # the AX = XB rotation held, the rest on every image point
    kinematic: KinematicResult | None = None  # with the arm's geometry fitted too

    @property
    def T_flange_camera(self) -> NDArray[np.float64]:
        if self.chosen == "kinematic":
            if self.kinematic is None:
                raise ValueError("no kinematic fit was run")
            return self.kinematic.T_flange_camera
        if self.chosen in ("joint", "hybrid"):
            refined = self.joint if self.chosen == "joint" else self.hybrid
            if refined is None:
                raise ValueError(f"no {self.chosen} refinement was run")
            return refined.T_flange_camera
        return self.methods[self.chosen].T_flange_camera

    def solution(self) -> HandEyeSolution:
        """The report as the hand-eye solution every interface publishes."""
        return HandEyeSolution(
            chosen=self.chosen,
            T_flange_camera=Pose.from_T(self.T_flange_camera),
            methods={name: m.solution() for name, m in self.methods.items()},
            joint=None if self.joint is None else self._joint_solution(self.joint),
            hybrid=None if self.hybrid is None else RefinedSolution(
                T_flange_camera=Pose.from_T(self.hybrid.T_flange_camera),
                T_base_board=Pose.from_T(self.hybrid.T_base_board),
                rms_px=self.hybrid.rms_px,
                per_view_rms_px=[float(v) for v in self.hybrid.per_view_rms_px],
                std_position_mm=[float(v) for v in self.hybrid.std_position_mm],
                converged=self.hybrid.converged),
            kinematic=None if self.kinematic is None else KinematicSolution(
                T_flange_camera=Pose.from_T(self.kinematic.T_flange_camera),
                T_base_board=Pose.from_T(self.kinematic.T_base_board),
                rms_px=self.kinematic.rms_px,
                per_view_rms_px=[float(v) for v in self.kinematic.per_view_rms_px],
                dh_delta_theta_rad=[float(v) for v in self.kinematic.delta_theta_rad],
                dh_delta_d_mm=[float(v) for v in self.kinematic.delta_d_mm],
                dh_delta_a_mm=[float(v) for v in self.kinematic.delta_a_mm],
                converged=self.kinematic.converged),
            views=[ViewFit(name=n, pnp_rms_px=float(r))
                   for n, r in zip(self.view_names, self.pnp_rms_px, strict=True)],
            skipped_views=list(self.skipped_views),
            verdict=CalibrationVerdict(consistent=self.verdict.consistent,
                                       findings=list(self.verdict.findings),
                                       text=self.verdict.text))

    def _joint_solution(self, joint: JointResult) -> JointSolution:
        extra: dict[str, Any] = {}
        if self.joint_spread is not None:
            extra["residual"] = MeanResidual(mean_mm=self.joint_spread.mean_mm,
                                             mean_deg=self.joint_spread.mean_deg)
        free = self.joint_free_intrinsics
        if free is not None:
            c = free.camera
            extra["free_intrinsics"] = FreeIntrinsics(rms_px=free.rms_px, fx=c.fx, fy=c.fy,
                                                      cx=c.cx, cy=c.cy)
        return JointSolution(
            T_flange_camera=Pose.from_T(joint.T_flange_camera),
            T_base_board=Pose.from_T(joint.T_base_board),
            rms_px=joint.rms_px,
            per_view_rms_px=[float(v) for v in joint.per_view_rms_px],
            std_position_mm=[float(v) for v in joint.std_position_mm],
            std_rotvec_deg=[float(v) for v in joint.std_rotvec_deg],
            converged=joint.converged, **extra)

    def summary(self) -> str:
        """Plain-text table for people at the cell."""
        lines = [f"views used: {len(self.view_names)}"
                 + (f" (board not found in: {', '.join(self.skipped_views)})"
                    if self.skipped_views else "")]
        for name, m in self.methods.items():
            p = pose_dict(m.T_flange_camera)
            lines.append(
                f"{name:>7}: position_mm {_fmt(p['position_mm'])}  rotvec_rad "
                f"{_fmt(p['rotvec_rad'], 5)}  residual {m.spread.mean_mm:.2f} mm / "
                f"{m.spread.mean_deg:.3f} deg"
            )
        if self.joint is not None:
            p = pose_dict(self.joint.T_flange_camera)
            lines.append(
                f"  joint: position_mm {_fmt(p['position_mm'])}  rotvec_rad "
                f"{_fmt(p['rotvec_rad'], 5)}  reprojection rms {self.joint.rms_px:.2f} px"
            )
        if self.hybrid is not None:
            p = pose_dict(self.hybrid.T_flange_camera)
            lines.append(
                f" hybrid: position_mm {_fmt(p['position_mm'])}  rotvec_rad "
                f"{_fmt(p['rotvec_rad'], 5)}  reprojection rms {self.hybrid.rms_px:.2f} px"
            )
        if self.kinematic is not None:
            p = pose_dict(self.kinematic.T_flange_camera)
            lines.append(
                f"kinematic: position_mm {_fmt(p['position_mm'])}  rotvec_rad "
                f"{_fmt(p['rotvec_rad'], 5)}  reprojection rms {self.kinematic.rms_px:.2f} px"
            )
        lines.append(f"chosen: {self.chosen}")
        lines.append(self.verdict.text)
        return "\n".join(lines)


def _fmt(values: list[float], digits: int = 2) -> str:
    return "[" + ", ".join(f"{v:.{digits}f}" for v in values) + "]"


def judge(
    view_names: tuple[str, ...],
    pnp_rms_px: tuple[float, ...],
    methods: dict[str, MethodResult],
    joint: JointResult | None,
    joint_free_intrinsics: JointResult | None,
    chosen: str,
    mean_depth_mm: float,
    focal_px: float,
    hybrid: JointResult | None = None,
    kinematic: KinematicResult | None = None,
) -> Verdict:
    """Plain-words findings; ``consistent`` is False when any finding is a contradiction.
    With ``chosen == "kinematic"`` the joint refinement's disagreement is explained by the
    arm's geometry and is not one."""
    findings: list[str] = []
    consistent = True
    pnp = np.asarray(pnp_rms_px, dtype=float)
    bad = [f"{n} ({r:.2f} px)" for n, r in zip(view_names, pnp, strict=True)
           if r > PNP_RMS_LIMIT_PX]
    if bad:
        consistent = False
        findings.append(
            f"Some images are not explained by the intrinsics even on their own: {', '.join(bad)}."
            " Check that the camera file matches this camera and resolution and that the board"
            " was detected correctly in those images."
        )
    names = list(methods)
    worst = (0.0, 0.0, "", "")
    for i, a in enumerate(names):
        for b in names[i + 1:]:
            d_mm, d_deg = pose_distance(methods[a].T_flange_camera, methods[b].T_flange_camera)
            if d_mm > worst[0] or d_deg > worst[1]:
                worst = (max(d_mm, worst[0]), max(d_deg, worst[1]), a, b)
    if worst[0] > METHOD_SPREAD_LIMIT_MM or worst[1] > METHOD_SPREAD_LIMIT_DEG:
        consistent = False
        findings.append(
            f"The AX = XB methods disagree by up to {worst[0]:.2f} mm / {worst[1]:.3f} deg: "
            "the robot motions are too small or rotate about too few axes for a stable answer;"
            " add views tilted by 20-40 deg about different axes."
        )
    elif len(names) > 1:
        findings.append(
            f"The AX = XB methods ({', '.join(names)}) agree within {worst[0]:.2f} mm / "
            f"{worst[1]:.3f} deg."
        )
    if chosen == "kinematic":
        # the closed-form methods share the nominal kinematics' error: their spread is no
        # contradiction once the arm's geometry explains the images
        consistent = not bad
    if chosen == "hybrid" and hybrid is not None and joint is not None:
        findings.extend(_judge_hybrid(pnp, hybrid, joint, joint_free_intrinsics,
                                      mean_depth_mm, focal_px))
        consistent = consistent and findings[-1].startswith("The hybrid explains")
    elif joint is not None:
        findings.append(_judge_joint(pnp, methods, joint, joint_free_intrinsics,
                                     "joint" if chosen == "kinematic" else chosen,
                                     mean_depth_mm, focal_px))
        if chosen != "kinematic":
            consistent = consistent and findings[-1].startswith("The joint refinement explains")
    if joint is not None and kinematic is not None:
        findings.append(_judge_kinematic(joint, kinematic, chosen))
    return Verdict(consistent, tuple(findings))


def kinematic_explains(joint: JointResult, kinematic: KinematicResult,
                       pnp_rms_px: NDArray[np.float64] | Sequence[float]) -> bool:
    """Whether the arm's fitted geometry explains the images that the nominal one does not:
    the kinematic fit is within what the images allow and well below the joint rms."""
    allowed = max(JOINT_RMS_LIMIT_PX, JOINT_RMS_FACTOR * float(np.median(pnp_rms_px)))
    return (kinematic.converged and kinematic.rms_px <= allowed
            and kinematic.rms_px < KINEMATIC_BLAME_FACTOR * joint.rms_px)


def _judge_kinematic(joint: JointResult, kinematic: KinematicResult, chosen: str) -> str:
    k = kinematic
    d_mm, d_deg = pose_distance(k.T_flange_camera, joint.T_flange_camera)
    if chosen != "kinematic":
        if k.rms_px < KINEMATIC_BLAME_FACTOR * joint.rms_px:
            return (f"Fitting the arm's geometry with the mount lowers the rms from "
                    f"{joint.rms_px:.2f} px to {k.rms_px:.2f} px (the kinematic result, "
                    f"{d_mm:.2f} mm / {d_deg:.3f} deg from the joint one).")
        return (f"Fitting the arm's geometry with the mount gives {k.rms_px:.2f} px rms against "
                f"{joint.rms_px:.2f} px: the arm's kinematics are not what the data disagree on.")
    theta_mrad = 1000.0 * float(np.max(np.abs(k.delta_theta_rad)))
    length_mm = float(max(np.max(np.abs(k.delta_d_mm)), np.max(np.abs(k.delta_a_mm))))
    return (
        f"The arm's reported poses disagree with its nominal kinematics: fitting the arm's "
        f"geometry with the mount lowers the rms from {joint.rms_px:.2f} px to {k.rms_px:.2f} px"
        f" (joint angle offsets up to {theta_mrad:.2f} mrad, link lengths up to "
        f"{length_mm:.2f} mm off the published table) and moves the mount by {d_mm:.2f} mm / "
        f"{d_deg:.3f} deg from the joint result. The kinematic result is chosen. The cell does "
        "not correct the arm's reported poses with this geometry: approaches that finish on "
        "their own closing views (servo, look-and-move's last cycles) do not need it."
    )


def _judge_hybrid(
    pnp: NDArray[np.float64],
    hybrid: JointResult,
    joint: JointResult,
    free: JointResult | None,
    mean_depth_mm: float,
    focal_px: float,
) -> list[str]:
    """Findings about the hybrid; the last starts with "The hybrid explains" if it is good.

    The hybrid holds the motions' rotation, so only its reprojection rms can contradict it
    (the flange poses and the images disagree by more than the images' own noise allows). How
    far the free joint fit turns away from it is reported, not held against it: the images
    barely see the mount's roll about the optical axis, and flange poses a few tenths of a
    millimetre off (an arm on its nominal kinematics) turn the free fit by tenths of a degree
    there while the motions' rotations stay within hundredths."""
    allowed = max(JOINT_RMS_LIMIT_PX, JOINT_RMS_FACTOR * float(np.median(pnp)))
    findings = []
    median = float(np.median(pnp))
    if not joint_is_trusted(joint.rms_px, pnp):
        findings.append(
            f"The free joint fit leaves {joint.rms_px:.2f} px rms where each image alone leaves "
            f"{median:.2f} px (median): the robot's poses are off by more than the images' "
            "noise, so the rotation is taken from the motions (hybrid)."
        )
    d_mm, d_deg = pose_distance(joint.T_flange_camera, hybrid.T_flange_camera)
    if d_mm > METHOD_SPREAD_LIMIT_MM or d_deg > METHOD_SPREAD_LIMIT_DEG:
        findings.append(
            f"The free joint fit lands {d_mm:.2f} mm / {d_deg:.3f} deg from the hybrid: the "
            "images barely tell the mount's roll about the optical axis, and the robot's "
            "reported flange poses are off by tenths of a millimetre (an arm without kinematic "
            "calibration), which turns the free fit while the motions' rotations, which the "
            "hybrid keeps, do not move with them."
        )
    if hybrid.rms_px <= allowed:
        sigma = float(np.linalg.norm(hybrid.std_position_mm))
        findings.append(
            f"The hybrid explains all images with {hybrid.rms_px:.2f} px rms (rotation from "
            f"the motions, translation 1-sigma about {sigma:.2f} mm); the free joint fit is "
            f"{d_mm:.2f} mm / {d_deg:.3f} deg from it."
        )
        return findings
    text = (
        f"The hybrid leaves a reprojection rms of {hybrid.rms_px:.2f} px, although each image "
        f"alone fits its board pose to {float(np.median(pnp)):.2f} px (median): the robot poses "
        f"and the images disagree by about {hybrid.rms_px * mean_depth_mm / focal_px:.1f} mm "
        f"per view at the board's distance ({mean_depth_mm:.0f} mm)."
    )
    if free is not None and free.rms_px < INTRINSICS_BLAME_FACTOR * joint.rms_px:
        text += (f" Letting fx, fy, cx, cy move lowers the free fit's rms to {free.rms_px:.2f} "
                 "px: the intrinsics are the likely cause; recalibrate them (cell calibrate "
                 "intrinsics) at this resolution.")
    elif free is not None:
        text += (f" Letting fx, fy, cx, cy move only lowers the free fit's rms to "
                 f"{free.rms_px:.2f} px, so the intrinsics are not the main cause: the robot's "
                 "reported flange poses are off by millimetres (kinematic calibration, a pose "
                 "read while moving or in another frame).")
    findings.append(text)
    return findings


def _judge_joint(
    pnp: NDArray[np.float64],
    methods: dict[str, MethodResult],
    joint: JointResult,
    free: JointResult | None,
    chosen: str,
    mean_depth_mm: float,
    focal_px: float,
) -> str:
    """One finding about the joint fit; it starts with "The joint refinement explains" if good."""
    reference = chosen if chosen in methods else next(iter(methods))
    d_mm, d_deg = pose_distance(joint.T_flange_camera, methods[reference].T_flange_camera)
    allowed = max(JOINT_RMS_LIMIT_PX, JOINT_RMS_FACTOR * float(np.median(pnp)))
    rms_bad = joint.rms_px > allowed
    apart = d_mm > METHOD_SPREAD_LIMIT_MM or d_deg > METHOD_SPREAD_LIMIT_DEG
    if not rms_bad and not apart:
        sigma = float(np.linalg.norm(joint.std_position_mm))
        return (
            f"The joint refinement explains all images with {joint.rms_px:.2f} px rms "
            f"(T_flange_camera 1-sigma about {sigma:.2f} mm) and is {d_mm:.2f} mm / "
            f"{d_deg:.3f} deg from the {reference} result."
        )
    if rms_bad:
        mm_equiv = joint.rms_px * mean_depth_mm / focal_px
        text = (
            f"The joint refinement leaves a reprojection rms of {joint.rms_px:.2f} px, although "
            f"each image alone fits its board pose to {float(np.median(pnp)):.2f} px (median): no "
            "single T_flange_camera makes the robot poses agree with the images. At the board's"
            f" distance ({mean_depth_mm:.0f} mm) that is about {mm_equiv:.1f} mm of disagreement"
            " per view."
        )
    else:
        text = (
            f"The joint refinement fits the images ({joint.rms_px:.2f} px rms) but lands "
            f"{d_mm:.2f} mm / {d_deg:.3f} deg away from the AX = XB answer: the two ways of "
            "weighing the same data disagree."
        )
    if free is not None:
        if free.rms_px < INTRINSICS_BLAME_FACTOR * joint.rms_px:
            text += (
                f" Letting fx, fy, cx, cy move lowers the rms to {free.rms_px:.2f} px (fx "
                f"{free.camera.fx:.1f}, fy {free.camera.fy:.1f}, cx {free.camera.cx:.1f}, cy "
                f"{free.camera.cy:.1f}): the intrinsics are the likely cause; recalibrate them "
                "(cell calibrate intrinsics) at this resolution."
            )
        else:
            text += (
                f" Letting fx, fy, cx, cy move only lowers the rms to {free.rms_px:.2f} px, so the"
                " intrinsics are not the main cause: the robot's reported flange poses are off by "
                "millimetres (kinematic calibration, a pose read while moving or in another frame)."
            )
    if chosen == "joint":
        text += (
            f" The joint result differs from the {reference} result by {d_mm:.2f} mm / "
            f"{d_deg:.3f} deg; that difference is how far either can be trusted."
        )
    else:
        text += (
            f" The AX = XB result ({chosen}) and the joint result differ by {d_mm:.2f} mm / "
            f"{d_deg:.3f} deg; that difference is how far either can be trusted. The {chosen} "
            "result is the chosen one (it fits the robot motions); choose --method joint to "
            "prefer the fit to the images instead."
        )
    return text


def mount_fields(fixed_camera: bool, T_mount: NDArray[np.float64]) -> MountFields:
    """What a result's transform is, for readers of its ``T_flange_camera`` field: a fixed
    camera's result is ``T_base_camera`` (also given under that name)."""
    if not fixed_camera:
        return MountFields(mount="hand", transform="T_flange_camera")
    return MountFields(mount="fixed", transform="T_base_camera",
                       T_base_camera=Pose.from_T(T_mount))
