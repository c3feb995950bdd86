"""Does what the cell saw agree with itself? The check a result carries beside its numbers.

An approach's own error estimate (the last correction plus the reach error) is measured in the
base frame through the very calibration it relies on: with the camera mount off by 2 mm /
0.45 deg, every locate from one observation pose agrees with the last and the job reports
0.05 mm while the tool stands millimetres from the true goal. What can reveal such an error is
evidence the calibration must explain and does not:

- reprojection residuals: the intrinsics and the detection explain each image;
- the spread of the frames averaged into one locate: the arm and the target stood still;
- seen motion against reported motion: when the arm moves between two locates of a target at
  rest, the target's pose in the base frame must not change. ``T_base_target = T_base_flange
  @ T_flange_camera @ T_camera_target``: a wrong ``T_flange_camera`` (or intrinsics) maps the
  same target to different base poses from different arm poses, by about the mount error times
  the arm's rotation plus the mount's rotation error times its translation. A change beyond
  the tolerance means the hand-eye calibration (or the intrinsics, or the arm's kinematics) is
  inconsistent: code ``calibration_inconsistent``, the code ``apply`` refuses a
  self-contradictory calibration with.

Arm motions too small to reveal anything are reported and not judged.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from itertools import pairwise
from typing import Any, Protocol

import numpy as np
from numpy.typing import NDArray

from cell.error_codes import ErrorCode
from estimator.transforms import pose_distance

Matrix4 = NDArray[np.float64]


class Sighting(Protocol):
    """What the check reads of a locate (:class:`cell.vision.locate.Located`, which builds its
    own block with this module)."""

    @property
    def T_base_target(self) -> Matrix4: ...
    @property
    def T_base_tcp(self) -> Matrix4: ...
    @property
    def spread_mm(self) -> float: ...
    @property
    def spread_deg(self) -> float: ...
    @property
    def frame_rms_px(self) -> tuple[float, ...]: ...


@dataclass(frozen=True)
class ConsistencyLimits:
    """What the evidence may show and still count as consistent.

    The motion limits sit well above what the estimator's noise gives between two locates of a
    calibrated cell (0.05 mm / 0.07 deg at most on the simulated cell, docs/commissioning.md)
    and well below what a hand-measured mount gives (mm, tenths of a degree)."""

    rms_px: float = 1.0  # a frame's reprojection rms
    spread_mm: float = 0.5  # frames averaged into one locate, from their mean
    spread_deg: float = 0.2
    target_motion_mm: float = 0.5  # target centre's change in the base frame between locates
    target_motion_deg: float = 0.15
    # the arm must move at least this much between two locates for the pair to be judged
    min_arm_motion_mm: float = 5.0
    min_arm_motion_deg: float = 2.0


DEFAULT_LIMITS = ConsistencyLimits()


@dataclass(frozen=True)
class MotionCheck:
    """Two locates of a target at rest from two arm poses."""

    between: tuple[str, str]
    arm_moved_mm: float
    arm_moved_deg: float
    target_moved_mm: float  # the target centre, in the base frame
    target_moved_deg: float
    judged: bool  # the arm moved enough for the pair to reveal a calibration error
    ok: bool

    def as_dict(self) -> dict[str, Any]:
        return {"between": list(self.between), "arm_moved_mm": self.arm_moved_mm,
                "arm_moved_deg": self.arm_moved_deg, "target_moved_mm": self.target_moved_mm,
                "target_moved_deg": self.target_moved_deg, "judged": self.judged, "ok": self.ok}


def _centre_pose(T_base_target: Matrix4, centre_mm: NDArray[np.float64]) -> Matrix4:
    T = np.array(T_base_target, dtype=float)
    T[:3, 3] = T[:3, :3] @ centre_mm + T[:3, 3]
    return T


def motion_check(a: Sighting, b: Sighting, names: tuple[str, str],
                 centre_mm: NDArray[np.float64], limits: ConsistencyLimits) -> MotionCheck:
    """Compare the arm's reported motion between two locates with the target's seen motion."""
    arm_mm, arm_deg = pose_distance(a.T_base_tcp, b.T_base_tcp)
    t_mm, t_deg = pose_distance(_centre_pose(a.T_base_target, centre_mm),
                                _centre_pose(b.T_base_target, centre_mm))
    judged = arm_mm >= limits.min_arm_motion_mm or arm_deg >= limits.min_arm_motion_deg
    ok = not judged or (t_mm <= limits.target_motion_mm and t_deg <= limits.target_motion_deg)
    return MotionCheck(names, arm_mm, arm_deg, t_mm, t_deg, judged, ok)


def consistency(locates: Sequence[tuple[str, Sighting]], centre_mm: NDArray[np.float64],
                limits: ConsistencyLimits = DEFAULT_LIMITS, target_at_rest: bool = True
                ) -> dict[str, Any]:
    """The ``consistency`` block of a result from its named locates, in the order taken.

    ``target_at_rest`` False (a conveyor, a single locate): no motion is judged, since a
    change of the target's base pose is then expected."""
    centre = np.asarray(centre_mm, dtype=float)
    rms = [float(r) for _, loc in locates for r in loc.frame_rms_px]
    max_rms = max(rms) if rms else 0.0
    spread_mm = max((loc.spread_mm for _, loc in locates), default=0.0)
    spread_deg = max((loc.spread_deg for _, loc in locates), default=0.0)
    checks = ([motion_check(a, b, (na, nb), centre, limits)
               for (na, a), (nb, b) in pairwise(locates)]
              if target_at_rest else [])
    judged = [c for c in checks if c.judged]
    findings: list[dict[str, Any]] = []
    if max_rms > limits.rms_px:
        findings.append({"code": ErrorCode.reprojection_too_large.value, "text":
                         f"a frame's reprojection rms is {max_rms:.2f} px (limit "
                         f"{limits.rms_px} px): intrinsics or detection do not explain it"})
    if spread_mm > limits.spread_mm or spread_deg > limits.spread_deg:
        findings.append({"code": ErrorCode.spread_too_large.value, "text":
                         f"the frames of one locate spread {spread_mm:.2f} mm / "
                         f"{spread_deg:.3f} deg (limit {limits.spread_mm} mm / "
                         f"{limits.spread_deg} deg): the arm or the target was not at rest"})
    bad = [c for c in judged if not c.ok]
    if bad:
        worst = max(bad, key=lambda c: c.target_moved_mm)
        findings.append({"code": ErrorCode.calibration_inconsistent.value, "text":
                         f"the arm moved {worst.arm_moved_mm:.1f} mm / {worst.arm_moved_deg:.1f} "
                         f"deg between {worst.between[0]} and {worst.between[1]} and the target "
                         f"at rest seemed to move {worst.target_moved_mm:.2f} mm / "
                         f"{worst.target_moved_deg:.3f} deg in the base frame (limit "
                         f"{limits.target_motion_mm} mm / {limits.target_motion_deg} deg): the "
                         "hand-eye calibration or the intrinsics are off; recalibrate "
                         "(docs/commissioning.md)"})
    if findings:
        verdict = "inconsistent"
    elif judged:
        verdict = "consistent"
    else:
        verdict = "unchecked"  # residuals and spread fine, but no motion to test the calibration
    return {
        "verdict": verdict,
        "codes": [f["code"] for f in findings],
        "findings": [f["text"] for f in findings],
        "reprojection": {"rms_px": rms, "max_rms_px": max_rms, "limit_px": limits.rms_px},
        "frame_spread": {"max_mm": spread_mm, "max_deg": spread_deg,
                         "limit_mm": limits.spread_mm, "limit_deg": limits.spread_deg},
        "motion": {
            "target_at_rest": target_at_rest,
            "checks": [c.as_dict() for c in checks],
            "judged": len(judged),
            "max_target_moved_mm": max((c.target_moved_mm for c in judged), default=None),
            "max_target_moved_deg": max((c.target_moved_deg for c in judged), default=None),
            "limit_mm": limits.target_motion_mm, "limit_deg": limits.target_motion_deg,
            "min_arm_motion_mm": limits.min_arm_motion_mm,
            "min_arm_motion_deg": limits.min_arm_motion_deg,
        },
    }
