"""What a finished pick returns: which part it took, how the grip went, where the part should
end, and how long each phase took.

A PLC reads ``part.id`` (the instance the cell chose, stable while the part stays put),
``grip.verdict`` (``held``: the fingers stopped on an object inside the recipe's width window)
and ``phases_s`` (``locate``, ``approach``, ``grasp``, ``verify``, ``retract``, ``place``:
only the phases the pick ran) with ``cycle_s`` for the whole. ``place`` is present when the
pick placed the part: the taught place pose and ``T_base_part_goal``, where the part should be
once released (the place pose carried through the grip the pick measured).
"""

from __future__ import annotations

from typing import Literal

from cell.results.approach import ApproachResult
from cell.results.base import Result
from cell.results.pose import Pose

PickPhase = Literal["locate", "approach", "grasp", "verify", "retract", "place"]
GripVerdict = Literal["held", "missed", "out_of_window"]


class PickedPart(Result):
    """The part the pick chose: its id in the locate it was chosen from, its pose then, and
    how many parts that locate saw."""

    id: int
    layout: str
    T_base_target: Pose
    parts_seen: int


class Grip(Result):
    """The gripper's word after closing: whether it stopped on an object, where the fingers
    stopped, and the window the recipe accepts."""

    verdict: GripVerdict
    object_detected: bool
    width_mm: float
    window_mm: tuple[float, float]


class Place(Result):
    """Where the pick put the part: the taught pose's name, the tool pose it released at, and
    where the part should be now."""

    taught: str
    T_base_tcp: Pose
    T_base_part_goal: Pose


class PickResult(Result):
    part: PickedPart
    approach: ApproachResult
    grasp_T_base_tcp: Pose
    grip: Grip
    retracted_T_base_tcp: Pose
    place: Place | None
    phases_s: dict[PickPhase, float]
    cycle_s: float
