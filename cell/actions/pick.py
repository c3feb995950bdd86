"""The pick: locate, choose a part, approach its pre-pick pose, grasp, verify, retract, place.

One job holds the motion slot for the whole cycle, so a PLC sends one command and reads one
result (:class:`cell.results.pick.PickResult`). Every pose the cycle will visit is known once
the part is chosen, and every leg between them is checked before the job starts (the guard's
box, tilt and reach along each straight path): a part the arm cannot take is refused with the
leg named, and nothing moves.

The phases:

- ``locate``: every part in view, of the layout and of the recipe's other targets (a second
  product in the same view is told apart, not taken for parts with dots missing); the
  configured order (``[locate] order``) picks the next part of the layout, which the pick's
  own locates then follow among the others. The cycle's time starts here.
- ``approach``: to the pre-pick pose (the standoff back along the tool axis), closing on the
  part as an approach does (look-and-move or the servo); its refined pose sets the grasp.
- ``grasp``: blind along the tool axis to the grasp pose at the grasp speed.
- ``verify``: close; the grip holds when the gripper stopped on an object with the fingers
  inside the window. No object: open, retract, fail ``grasp_missed``; an object outside the
  window: the same, ``grip_out_of_window``; a gripper fault: the arm stops, ``gripper_fault``.
- ``retract``: back along the tool axis by the retract distance, then, if one is named, to a
  taught base-frame retract pose.
- ``place`` (when asked): above the taught place pose, down to it, open, back up.

A stop in any phase leaves the arm still and the fingers as they are; the job ends
``cancelled`` with the phase and the gripper's state in its message.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Iterator, Mapping
from contextlib import contextmanager
from dataclasses import dataclass
from typing import Any, Protocol

import numpy as np
from numpy.typing import NDArray

from cell.actions.approach import (
    ApproachPlan,
    JobLayout,
    locate,
    observation_tcp,
    pose_approach,
)
from cell.actions.approach_rules import check_standoff
from cell.core import CellCore
from cell.error_codes import ErrorCode
from cell.errors import Cancelled, CellError, LimitError, RefusedError, UnavailableError
from cell.jobs.store import Job
from cell.motion.guard import Motion
from cell.results.modes import ApproachMode
from cell.results.pick import Grip, GripVerdict, PickedPart, PickPhase, PickResult, Place
from cell.results.pose import Pose
from cell.vision.frames import approach_tcp
from cell.vision.locate import IN_USE, Located
from estimator import Target
from estimator.transforms import invert_T, pose_dict, translation_T

log = logging.getLogger(__name__)
Matrix4 = NDArray[np.float64]
Layouts = Mapping[str, Target]


class GripperCommands(Protocol):
    """What the pick asks of the cell's gripper (:class:`cell.supervision.gripper.
    GripperService`): commands sent inside the pick's motion, and the last status."""

    def command(self, caller: str, action: str, position_mm: float | None = None,
                speed_pct: float = 100.0, force_pct: float = 50.0, wait: bool = True,
                motion: Motion | None = None) -> dict[str, Any]: ...

    def status(self) -> dict[str, Any] | None: ...


@dataclass(frozen=True)
class PickPlan:
    """What a pick was asked to do, with every default resolved."""

    approach: ApproachPlan
    mode: ApproachMode  # look_and_move or servo
    grasp_speed_mm_s: float
    retract_mm: float
    grip_window_mm: tuple[float, float]
    place_name: str | None
    T_base_tcp_place: Matrix4 | None
    place_clearance_mm: float
    place_speed_mm_s: float
    retract_name: str | None = None  # a base-frame pose the retract ends at
    T_base_tcp_retract: Matrix4 | None = None

    def params(self) -> dict[str, Any]:
        a = self.approach
        return {"standoff_mm": a.standoff_mm, "speed_mm_s": a.speed_mm_s,
                "T_target_tcp": pose_dict(a.T_target_tcp), "mode": self.mode,
                "grasp_speed_mm_s": self.grasp_speed_mm_s, "retract_mm": self.retract_mm,
                "grip_window_mm": list(self.grip_window_mm), "place": self.place_name,
                "retract": self.retract_name}


@dataclass(frozen=True)
class Legs:
    """The poses a pick visits once the part is chosen, in order."""

    T_base_target: Matrix4
    pre_pick: Matrix4
    grasp: Matrix4
    retract: Matrix4
    above_place: Matrix4 | None
    place: Matrix4 | None
    retract_to: Matrix4 | None = None  # the taught pose the retract ends at

    def named(self) -> list[tuple[str, Matrix4]]:
        out = [("pre-pick", self.pre_pick), ("grasp", self.grasp), ("retract", self.retract)]
        if self.retract_to is not None:
            out.append(("taught retract pose", self.retract_to))
        if self.above_place is not None and self.place is not None:
            out += [("above the place pose", self.above_place), ("place", self.place),
                    ("retract from the place pose", self.above_place)]
        return out


def legs_for(plan: PickPlan, T_base_target: Matrix4) -> Legs:
    a = plan.approach
    grasp = approach_tcp(T_base_target, a.T_target_tcp, 0.0)
    above = None if plan.T_base_tcp_place is None else (
        plan.T_base_tcp_place @ translation_T(0.0, 0.0, -plan.place_clearance_mm))
    return Legs(T_base_target=T_base_target,
                pre_pick=approach_tcp(T_base_target, a.T_target_tcp, a.standoff_mm),
                grasp=grasp, retract=grasp @ translation_T(0.0, 0.0, -plan.retract_mm),
                above_place=above, place=plan.T_base_tcp_place,
                retract_to=plan.T_base_tcp_retract)


@dataclass(frozen=True)
class Chosen:
    """The part a pick takes: its id and layout in the locate of every part, that part located
    on its own (followed among the others), and how many parts the locate saw."""

    part_id: int
    layout: str
    located: Located
    parts_seen: int


def choose_part(core: CellCore, n_frames: int, beside: Layouts | None = None,
                name: str = IN_USE) -> Chosen:
    """The first pickable part of the layout in use (called ``name``) in the configured order
    (``[locate] order``) of one locate of every part in view, of that layout and of the
    ``beside`` ones (a recipe's other targets: a product that shares the view is explained
    as its own parts, never taken for one of this layout's with dots missing); from then on
    the locator follows that part (:meth:`cell.vision.locate.Locator.follow`), so the pick's
    own locates see it and not its neighbours. The caller ends the following."""
    others = {k: v for k, v in (beside or {}).items() if k != name}
    parts = core.locator.locate_all({**others, name: core.locator.target})
    mine = [p for p in parts.instances if p.layout == name]
    pickable = [p for p in mine if p.pickable]
    if not pickable:
        why = "; ".join(f"part {p.id}: {' '.join(p.reasons)}" for p in mine)
        n_other = len(parts.instances) - len(mine)
        raise RefusedError(ErrorCode.target_not_visible,
                           f"no part to pick in view: {len(mine)} part(s) of the layout seen"
                           + (f" ({why})" if why else "")
                           + (f", {n_other} of the recipe's other targets" if n_other else ""))
    part = pickable[0]
    core.locator.follow(np.asarray(part.centre_base_mm, dtype=float), others)
    return Chosen(part.id, part.layout, locate(core, n_frames), len(parts.instances))


class Phases:
    """Each phase's seconds, and the phase the pick is in (for the job's progress and a stop's
    message). While the pick approaches, the job's progress shows the approach's own steps
    (``observe``, ``locate``, ``final`` or the servo's figures), as an approach job's does."""

    def __init__(self, core: CellCore, job_id: str, part: dict[str, Any],
                 began_s: float) -> None:
        self.core, self.job_id, self.part = core, job_id, part
        self.seconds: dict[PickPhase, float] = {}
        self.current: PickPhase | None = None
        self.began_s = began_s  # the first locate's start: the cycle counts it

    @contextmanager
    def phase(self, name: PickPhase) -> Iterator[None]:
        self.current = name
        self.core.runner.progress(self.job_id, {"phase": name, "part": self.part,
                                                "phases_s": dict(self.seconds)})
        t0 = time.monotonic()
        yield
        self.seconds[name] = round(time.monotonic() - t0, 4)

    def cycle_s(self) -> float:
        return round(time.monotonic() - self.began_s, 4)


def grip_verdict(status: dict[str, Any], window_mm: tuple[float, float]) -> GripVerdict:
    if not status.get("object_detected"):
        return "missed"
    width = float(status.get("position_mm", float("nan")))
    return "held" if window_mm[0] <= width <= window_mm[1] else "out_of_window"


def start_pick(core: CellCore, gripper: GripperCommands | None, caller: str, plan: PickPlan, *,
               recipe: dict[str, Any] | None = None, layout: Target | None = None,
               layout_name: str = IN_USE, beside: Layouts | None = None,
               wait: bool = False, wait_timeout_s: float = 180.0) -> Job:
    """Start a pick job (see the module doc) of a part of ``layout`` (None: the cell's
    target), called ``layout_name`` in the result, among parts of ``beside`` layouts that
    may share the view; refusals (no gripper, the arm or camera not ready, no part, a leg the
    guard refuses) move nothing and create no job."""
    params = plan.params()
    if recipe is not None:
        params["recipe"] = recipe
    chosen: list[Chosen] = []
    lent = JobLayout(core, layout)
    first_locate_s: list[tuple[float, float]] = []  # (start, seconds)

    def checks(motion: Motion) -> None:
        if gripper is None or gripper.status() is None:
            raise UnavailableError(ErrorCode.gripper_unavailable,
                                   "this cell has no gripper: a pick needs one")
        check_standoff(plan.approach.standoff_mm)
        core.arm.guard.check_speed(plan.approach.speed_mm_s, plan.approach.accel_mm_s2)
        core.arm.guard.check_speed(plan.grasp_speed_mm_s, plan.approach.accel_mm_s2)
        core.arm.guard.check_speed(plan.place_speed_mm_s, plan.approach.accel_mm_s2)
        core.arm.ready_state()
        if not core.camera.is_connected:
            raise UnavailableError(ErrorCode.camera_lost, "the camera is lost: a pick needs it")
        t0 = time.monotonic()
        n_frames = 1 if plan.mode == ApproachMode.servo else core.config.approach.frames_per_locate
        try:
            part = choose_part(core, n_frames, beside, layout_name)
            first_locate_s.append((t0, time.monotonic() - t0))
            check_legs(core, legs_for(plan, part.located.T_base_target), plan)
        except BaseException:
            core.locator.follow(None)
            raise
        chosen.append(part)

    def work(job_id: str, motion: Motion) -> PickResult:
        try:
            return run_pick(core, gripper, caller, job_id, motion, plan, chosen[0],
                            *first_locate_s[0])
        finally:
            core.locator.follow(None)
            lent.ended()

    return lent.start_job("pick", caller, params, work, checks, wait=wait,
                          wait_timeout_s=wait_timeout_s)


def check_legs(core: CellCore, legs: Legs, plan: PickPlan,
               after_pre_pick: bool = False) -> None:
    """Every leg of the pick, from where the arm is, through the guard: the box, the tilt
    and the arm's reach along each straight path (``GuardedArm.check_reachable``); a
    look-and-move approach passes its observation pose first. ``after_pre_pick``: the legs
    after the pre-pick pose, from the pre-pick pose reached. The first refusal names its
    leg; nothing moves."""
    named = legs.named()
    if after_pre_pick:
        named = named[1:]
    elif plan.mode == ApproachMode.look_and_move and not core.frames.is_fixed:
        named = [("observation", observation_tcp(core, legs.T_base_target,
                                                 plan.approach.T_target_tcp)), *named]
    core.arm.check_reachable([(f"pick {name}", T) for name, T in named]
                             ).raise_if_unreachable()


def run_pick(core: CellCore, gripper: GripperCommands | None, caller: str, job_id: str,
             motion: Motion, plan: PickPlan, part: Chosen, located_at_s: float,
             locate_s: float) -> PickResult:
    """The cycle from the part chosen; ``located_at_s``: when the first locate began (the
    cycle's start), ``locate_s`` how long it took."""
    assert gripper is not None
    phases = Phases(core, job_id, {
        "id": part.part_id, "layout": part.layout,
        "T_base_target": pose_dict(part.located.T_base_target), "parts_seen": part.parts_seen},
        located_at_s)
    phases.seconds["locate"] = round(locate_s, 4)
    try:
        return _cycle(core, gripper, caller, job_id, motion, plan, part, phases)
    except Cancelled as err:
        raise Cancelled(err.code, f"{err.message} (pick phase {phases.current}; "
                        f"{_gripper_words(gripper)})") from err


def _cycle(core: CellCore, gripper: GripperCommands, caller: str, job_id: str, motion: Motion,
           plan: PickPlan, part: Chosen, phases: Phases) -> PickResult:
    a = plan.approach
    with phases.phase("approach"):
        approached = pose_approach(core, job_id, motion, part.located, a, plan.mode,
                                   {"first_locate_s": phases.seconds["locate"]})
    T_base_target = approached.T_base_target.T()
    legs = legs_for(plan, T_base_target)
    check_legs(core, legs, plan, after_pre_pick=True)
    with phases.phase("grasp"):
        core.arm.move_linear(legs.grasp, plan.grasp_speed_mm_s, a.accel_mm_s2, what="grasp")
    T_grasp_reached = core.arm.state().T_base_tcp
    with phases.phase("verify"):
        status = _gripper(gripper, caller, "close", motion, core)
        verdict = grip_verdict(status, plan.grip_window_mm)
    grip = Grip(verdict=verdict, object_detected=bool(status.get("object_detected")),
                width_mm=float(status.get("position_mm", float("nan"))),
                window_mm=plan.grip_window_mm)
    if verdict != "held":
        _let_go(core, gripper, caller, motion, plan, legs.retract)
        if verdict == "missed":
            raise RefusedError(ErrorCode.grasp_missed,
                               f"no object between the fingers after closing at the grasp pose "
                               f"of part {part.part_id} (fingers at {grip.width_mm:.1f} mm); "
                               "the gripper opened and the arm retracted")
        raise RefusedError(ErrorCode.grip_out_of_window,
                           f"the fingers stopped at {grip.width_mm:.1f} mm on part "
                           f"{part.part_id}, outside the window {plan.grip_window_mm[0]:g}-"
                           f"{plan.grip_window_mm[1]:g} mm; the gripper opened and the arm "
                           "retracted")
    with phases.phase("retract"):
        core.arm.move_linear(legs.retract, a.speed_mm_s, a.accel_mm_s2, what="retract")
        if legs.retract_to is not None:
            core.arm.move_linear(legs.retract_to, a.speed_mm_s, a.accel_mm_s2,
                                 what="the taught retract pose")
    place = None
    if legs.place is not None and legs.above_place is not None:
        assert plan.place_name is not None
        T_tcp_part = invert_T(T_grasp_reached) @ T_base_target
        with phases.phase("place"):
            core.arm.move_linear(legs.above_place, a.speed_mm_s, a.accel_mm_s2,
                                 what="above the place pose")
            core.arm.move_linear(legs.place, plan.place_speed_mm_s, a.accel_mm_s2,
                                 what="place pose")
            T_released = core.arm.state().T_base_tcp
            _gripper(gripper, caller, "open", motion, core)
            core.arm.move_linear(legs.above_place, a.speed_mm_s, a.accel_mm_s2,
                                 what="retract from the place pose")
        place = Place(taught=plan.place_name, T_base_tcp=Pose.from_T(T_released),
                      T_base_part_goal=Pose.from_T(legs.place @ T_tcp_part))
    return PickResult(
        part=PickedPart(id=part.part_id, layout=part.layout,
                        T_base_target=Pose.from_T(T_base_target), parts_seen=part.parts_seen),
        approach=approached, grasp_T_base_tcp=Pose.from_T(T_grasp_reached), grip=grip,
        retracted_T_base_tcp=Pose.from_T(legs.retract if legs.retract_to is None
                                         else legs.retract_to), place=place,
        phases_s=dict(phases.seconds), cycle_s=phases.cycle_s())


def _gripper(gripper: GripperCommands, caller: str, action: str, motion: Motion,
             core: CellCore) -> dict[str, Any]:
    """One gripper command inside the pick's motion; a fault stops the arm and fails the pick
    ``gripper_fault`` (a stop stays a stop)."""
    try:
        status = gripper.command(caller, action, motion=motion)
    except Cancelled:
        raise
    except CellError as err:
        core.arm.settle()
        raise UnavailableError(ErrorCode.gripper_fault,
                               f"the gripper failed to {action}: {err.message}; the arm "
                               "stopped") from err
    if status.get("fault"):
        core.arm.settle()
        raise UnavailableError(ErrorCode.gripper_fault,
                               f"the gripper reports a fault after {action}: "
                               f"{status['fault']}; the arm stopped")
    return status


def _let_go(core: CellCore, gripper: GripperCommands, caller: str, motion: Motion,
            plan: PickPlan, T_retract: Matrix4) -> None:
    _gripper(gripper, caller, "open", motion, core)
    a = plan.approach
    core.arm.move_linear(T_retract, a.speed_mm_s, a.accel_mm_s2, what="retract")


def _gripper_words(gripper: GripperCommands) -> str:
    st = gripper.status()
    if not st:
        return "gripper state unknown"
    held = "holding an object" if st.get("object_detected") else "holding nothing"
    return f"gripper left as it was: {held}, fingers at {float(st.get('position_mm', 0)):.1f} mm"


def resolve_plan(core: CellCore, *, standoff_mm: float | None, speed_mm_s: float | None,
                 T_target_tcp: Matrix4 | None, mode: ApproachMode | None,
                 place: tuple[str, Matrix4] | None, grasp_speed_mm_s: float | None = None,
                 retract_mm: float | None = None,
                 grip_window_mm: tuple[float | None, float | None] = (None, None),
                 retract_to: tuple[str, Matrix4] | None = None) -> PickPlan:
    """A pick's plan: what was asked, the rest from ``[approach]`` and ``[pick]``."""
    ac, pc = core.config.approach, core.config.pick
    how = ac.mode if mode is None else mode
    if how not in (ApproachMode.look_and_move, ApproachMode.servo):
        raise LimitError(ErrorCode.invalid_request, f"a pick approaches by 'look_and_move' or "
                         f"'servo', got {how!r}")
    lo = pc.grip_min_mm if grip_window_mm[0] is None else float(grip_window_mm[0])
    hi = pc.grip_max_mm if grip_window_mm[1] is None else float(grip_window_mm[1])
    if not lo < hi:
        raise LimitError(ErrorCode.invalid_request, f"the grip window {lo:g}-{hi:g} mm is empty")
    return PickPlan(
        approach=ApproachPlan(
            standoff_mm=ac.standoff_mm if standoff_mm is None else float(standoff_mm),
            speed_mm_s=ac.speed_mm_s if speed_mm_s is None else float(speed_mm_s),
            accel_mm_s2=min(ac.accel_mm_s2, core.config.limits.max_accel_mm_s2),
            T_target_tcp=ac.T_target_tcp.T() if T_target_tcp is None
            else np.asarray(T_target_tcp, dtype=float)),
        mode=how,
        grasp_speed_mm_s=pc.grasp_speed_mm_s if grasp_speed_mm_s is None
        else float(grasp_speed_mm_s),
        retract_mm=pc.retract_mm if retract_mm is None else float(retract_mm),
        grip_window_mm=(lo, hi), place_name=None if place is None else place[0],
        T_base_tcp_place=None if place is None else place[1],
        place_clearance_mm=pc.place_clearance_mm, place_speed_mm_s=pc.place_speed_mm_s,
        retract_name=None if retract_to is None else retract_to[0],
        T_base_tcp_retract=None if retract_to is None else retract_to[1])

