"""Every part in view, in the base frame: what a locate of all parts answers.

The estimator's instances (:mod:`estimator.instances`) mapped into the base frame with the arm
pose at the frame's capture, given ids that stay while the parts stay
(:mod:`cell.vision.instance_ids`) and put in the configured order
(:mod:`cell.vision.pick_order`).
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from cell.results.locate import (
    InstanceQuality,
    LocateAllResult,
    LocatedInstance,
    PickOrder,
    UnresolvedDots,
)
from cell.results.pose import Pose
from cell.vision.frames import CellFrames
from cell.vision.instance_ids import InstanceIds
from cell.vision.pick_order import ordered
from estimator import Target
from estimator.instances import Instance, InstanceSearch

Matrix4 = NDArray[np.float64]


@dataclass(frozen=True)
class LocatedParts:
    """The parts of one frame, ordered, and the frame they were seen in."""

    instances: tuple[LocatedInstance, ...]
    unresolved: tuple[UnresolvedDots, ...]
    order: PickOrder
    layouts: tuple[str, ...]
    T_base_tcp: Matrix4
    frame_timestamp_s: float
    frame_sequence: int

    def answer(self, now_s: float) -> LocateAllResult:
        """The answer every interface publishes; ``now_s`` (time.monotonic()) dates the
        frame's age."""
        return LocateAllResult(
            instances=list(self.instances), unresolved=list(self.unresolved), order=self.order,
            layouts=list(self.layouts), T_base_tcp=Pose.from_T(self.T_base_tcp),
            frame_sequence=self.frame_sequence,
            frame_age_s=max(0.0, now_s - self.frame_timestamp_s))


def _quality(inst: Instance, target: Target) -> InstanceQuality:
    r = inst.pose
    return InstanceQuality(
        rms_px=float(r.rms_px),
        max_residual_px=float(np.max(r.residuals_px)) if len(r.residuals_px) else 0.0,
        ambiguous=bool(r.ambiguous), converged=bool(r.converged), identity=r.identity,
        n_points=len(r.matched_ids), n_dots=target.n_points,
        covariance=None if r.covariance is None else r.covariance.tolist())


def located_parts(search: InstanceSearch, layouts: Mapping[str, Target], frames: CellFrames,
                  T_base_tcp: Matrix4, ids: InstanceIds, order: PickOrder,
                  frame_timestamp_s: float, frame_sequence: int) -> LocatedParts:
    """The search's parts in the base frame, with their ids, in ``order``."""
    T_base_camera = frames.T_base_camera(T_base_tcp)
    placed = []
    for inst in search.instances:
        T_base_target = frames.T_base_target(T_base_tcp, inst.pose.T_camera_target)
        centre = layouts[inst.layout].points_mm.mean(axis=0)
        placed.append((inst, T_base_target, T_base_target[:3, :3] @ centre + T_base_target[:3, 3]))
    numbers = ids.assign([(inst.layout, centre) for inst, _, centre in placed])
    parts = [
        LocatedInstance(
            id=number, layout=inst.layout, T_base_target=Pose.from_T(T_base_target),
            T_camera_target=Pose.from_T(inst.pose.T_camera_target),
            centre_base_mm=(float(centre[0]), float(centre[1]), float(centre[2])),
            quality=_quality(inst, layouts[inst.layout]), flags=list(inst.flags),
            reasons=list(inst.reasons), pickable=not inst.flags)
        for number, (inst, T_base_target, centre) in zip(numbers, placed, strict=True)]
    unresolved = tuple(
        UnresolvedDots(n_dots=len(u.blobs), box_px=u.box_px, flags=list(u.flags),
                       reason=u.reason)
        for u in search.unresolved)
    return LocatedParts(tuple(ordered(parts, order, T_base_camera)), unresolved, order,
                        tuple(layouts), T_base_tcp, frame_timestamp_s, frame_sequence)
