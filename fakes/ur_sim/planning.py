"""Planning of profiled moves: from validated targets to commands the arm can run.

A controller checks the whole motion before the arm moves: a linear move is followed through
inverse kinematics along its length (reach, joint limits, singularities), a path is planned
segment by segment with its blends. A plan that cannot run is refused with a typed error and
nothing moves; a speed above the tool speed limit trips a protective stop, as UR's does.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np

from estimator.transforms import T_from_ur_pose, ur_pose_from_T
from fakes.ur_sim.arm_core import ArmCore
from fakes.ur_sim.commands import Command, MoveJ, MoveL
from fakes.ur_sim.kinematics import UnreachableError
from fakes.ur_sim.profiles import BlendedLinearPath, JointProfile, LinearProfile
from fakes.ur_sim.safety import SafetySupervisor
from fakes.ur_sim.state import (
    CommandRejectedError,
    PathEntry,
    PathKind,
    UnreachablePoseError,
    Vec,
    as_vector,
    positive_number,
)

_PATH_SAMPLE_MM = 5.0  # movel paths are checked through IK at least this densely
_PATH_SAMPLE_RAD = 0.05
_MAX_PATH_JOINT_STEP_RAD = 0.35  # a bigger jump between samples means a configuration flip


class MotionPlanner:
    """Plans moves of one arm from its kinematics and limits; callers hold the engine lock."""

    def __init__(self, core: ArmCore, safety: SafetySupervisor) -> None:
        self._core = core
        self._safety = safety

    def plan_j(self, q0: Vec, q1: Vec, speed: float, accel: float, cid: int, name: str
               ) -> MoveJ:
        """Synchronised trapezoidal joint move from ``q0`` to ``q1``."""
        self._safety.check_joint_limits(q1, "target")
        return MoveJ(cid, name, JointProfile(q0, q1, speed, accel))

    def plan_l(self, q0: Vec, pose6: Vec, speed: float, accel: float
               ) -> tuple[LinearProfile, Vec]:
        """Check the whole straight line through IK before accepting it; returns the end q."""
        limits, kin = self._core.limits, self._core.kin
        if speed > limits.max_tcp_speed_m_s:
            self._safety.trip(f"movel speed {speed:g} m/s exceeds the tool speed limit "
                              f"{limits.max_tcp_speed_m_s:g} m/s")
        T0 = kin.forward_tcp(q0)
        T1 = T_from_ur_pose(pose6.tolist())
        prof = LinearProfile(T0, T1, speed * 1000.0, accel * 1000.0, speed, accel)
        n = max(2, math.ceil(prof.length_mm / _PATH_SAMPLE_MM),
                math.ceil(prof.angle_rad / _PATH_SAMPLE_RAD))
        q = q0
        for u in np.linspace(0.0, 1.0, n + 1)[1:]:
            try:
                q_next = kin.inverse_tcp_local(prof.pose_at_progress(float(u)), q)
            except UnreachableError as err:
                raise UnreachablePoseError(
                    f"linear path to {list(pose6)} leaves the reachable workspace or the "
                    f"joint limits at {u:.0%} of the way") from err
            if float(np.max(np.abs(q_next - q))) > _MAX_PATH_JOINT_STEP_RAD:
                raise UnreachablePoseError(
                    f"linear path to {list(pose6)} passes through a singularity at {u:.0%}")
            q = q_next
        return prof, q

    def plan_path(self, cid: int, q: Vec, path: Sequence[PathEntry]) -> list[Command]:
        """The segments of a path starting at ``q``: runs of blended ``movel`` entries become
        one blended linear move, every other corner is a stop point."""
        segments: list[Command] = []
        run: list[LinearProfile] = []  # movel profiles to be blended together
        run_blends: list[float] = []
        run_first = 0
        for i, entry in enumerate(path):
            kind, tgt, v, a, blend = self.path_entry(i, entry)
            if kind == "movej_pose":
                tgt = self._core.ik(tgt, q)
            elif kind == "movel_joints":
                self._safety.check_joint_limits(tgt, f"path entry {i} target")
                tgt = np.asarray(ur_pose_from_T(self._core.kin.forward_tcp(tgt)))
            if kind in ("movej", "movej_pose"):
                if run:
                    segments.append(_blended(cid, run, run_blends[:-1], run_first))
                    run, run_blends = [], []
                seg = self.plan_j(q, tgt, v, a, cid, "movej")
                seg.progress = i
                segments.append(seg)
                q = tgt
                continue
            prof, q = self.plan_l(q, tgt, v, a)
            if run and run_blends[-1] > 0:
                limit_mm = 0.5 * min(run[-1].length_mm, prof.length_mm)
                if run_blends[-1] > limit_mm + 1e-9:
                    raise CommandRejectedError(
                        f"path entry {i - 1}: blend {run_blends[-1] / 1000:g} m exceeds "
                        f"half of a neighbouring segment ({limit_mm / 1000:g} m)")
                run.append(prof)
            else:
                if run:
                    segments.append(_blended(cid, run, run_blends[:-1], run_first))
                run, run_blends, run_first = [prof], [], i
            nxt = path[i + 1][0] if i + 1 < len(path) else None
            run_blends.append(blend * 1000.0 if nxt in ("movel", "movel_joints") else 0.0)
        if run:
            segments.append(_blended(cid, run, run_blends[:-1], run_first))
        return segments

    def path_entry(self, i: int, entry: PathEntry
                   ) -> tuple[PathKind, Vec, float, float, float]:
        """One waypoint, validated: (kind, target, speed, accel, blend_m)."""
        limits = self._core.limits
        try:
            kind, target, speed, accel, blend = entry
        except (TypeError, ValueError) as err:
            raise CommandRejectedError(
                f"path entry {i} must be (kind, target, speed, accel, blend)") from err
        b = float(blend)
        if not (math.isfinite(b) and b >= 0):
            raise CommandRejectedError(f"path entry {i}: blend must be >= 0")
        tgt = as_vector(target, 6, f"path entry {i} target")
        if kind in ("movej", "movej_pose"):
            v = positive_number(speed, f"path entry {i} speed", limits.max_joint_speed_rad_s)
            a = positive_number(accel, f"path entry {i} accel", limits.max_joint_accel_rad_s2)
        elif kind in ("movel", "movel_joints"):
            v = positive_number(speed, f"path entry {i} speed")
            a = positive_number(accel, f"path entry {i} accel", limits.max_tcp_accel_m_s2)
        else:
            raise CommandRejectedError(f"path entry {i}: unknown kind {kind!r}")
        return kind, tgt, v, a, b


def _blended(cid: int, run: list[LinearProfile], blends_mm: list[float], first: int) -> MoveL:
    return MoveL(cid, "movel", BlendedLinearPath(run, blends_mm), first)
