"""Approach: by look-and-move (observe, locate, correct, repeat, then the final move), by
closed-loop servoing (``mode="servo"``) or by image-based servoing to a taught view
(``mode="ibvs"``): the closed loop of :mod:`cell.servoing` with its position-based or
image-based law.

The goal is ``T_base_target @ T_target_tcp @ translate(0, 0, -standoff_mm)``. The arm first
goes to an observation pose in front of the target with the goal's orientation (so the final
move is a pure translation and every cycle sees the target from the same viewpoint), locates
again from frames exposed after it stopped, and repeats until the correction is under the
tolerance or the cycle limit; every cycle's correction and the final estimated error are in
the job's result. Every goal is checked before the job starts, so a refusal moves nothing.

A job with a recipe's dot layout (``layout``) has the locator look for that layout while the
job runs (its checks included) and brings the previous layout back when it ends; a refusal
leaves the locator exactly as it was (:class:`JobLayout`).

The estimated error goes through the calibration it relies on, so the result also says how it
was estimated (``estimated_error_basis``) and whether the evidence agrees with itself
(``consistency``, :mod:`cell.vision.consistency`): look-and-move locates the target from two
arm poses at least, and a target at rest that seems to move between them in the base frame
means the hand-eye calibration or the intrinsics are off.
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from cell.actions.approach_rules import check_standoff
from cell.core import CellCore
from cell.error_codes import ErrorCode
from cell.errors import CellError, LimitError, RefusedError, UnavailableError
from cell.jobs.runner import Work
from cell.jobs.store import Job
from cell.motion.guard import Motion
from cell.results import ApproachMode, IbvsApproach, LookAndMoveApproach, Pose, ServoApproach
from cell.results.approach import ClosingCorrection, ClosingNotSeen, ClosingStep, Cycle, ErrorBasis
from cell.results.consistency import Consistency
from cell.servoing.ibvs import Features
from cell.servoing.ibvs_mount import IbvsMount
from cell.servoing.image import ImageLaw
from cell.servoing.position import PositionLaw, ServoGoal
from cell.servoing.runner import ClosedLoop
from cell.vision.consistency import consistency
from cell.vision.frames import approach_tcp, observation_camera
from cell.vision.locate import Located
from estimator import Target
from estimator.transforms import invert_T, pose_dict, pose_distance

log = logging.getLogger(__name__)
Matrix4 = NDArray[np.float64]


@dataclass(frozen=True)
class ApproachPlan:
    standoff_mm: float
    speed_mm_s: float
    accel_mm_s2: float
    T_target_tcp: Matrix4


class JobLayout:
    """A dot layout lent to the locator for one job: :meth:`apply` when the job's checks
    begin, :meth:`refused` when they refuse (the locator's layout and last locate as they
    were), :meth:`ended` when the job ends (the previous layout back; the last locate, of the
    lent layout, dropped). ``target`` None: the locator's own layout, nothing to do."""

    def __init__(self, core: CellCore, target: Target | None) -> None:
        self._core = core
        self._target = target
        self._lock = threading.Lock()
        self._lent: tuple[Target, Located | None] | None = None  # what to bring back

    def apply(self) -> None:
        if self._target is None:
            return
        locator = self._core.locator
        with self._lock:
            previous = (locator.target, locator.last)
            if locator.use_target(self._target):
                self._lent = previous

    def checked(self, checks: Callable[[Motion], None]) -> Callable[[Motion], None]:
        """A job's pre-start ``checks`` run with the layout lent, and given back when they
        refuse."""
        def check(motion: Motion) -> None:
            self.apply()
            try:
                checks(motion)
            except BaseException:
                self.refused()
                raise
        return check

    def start_job(self, kind: str, caller: str, params: dict[str, Any], work: Work,
                  checks: Callable[[Motion], None], *, wait: bool,
                  wait_timeout_s: float) -> Job:
        """Start a camera job with the layout lent to it (:meth:`checked`); given back when no
        job starts after all."""
        try:
            return self._core.runner.start(kind, caller, params, work,
                                           check=self.checked(checks), needs_camera=True,
                                           wait=wait, wait_timeout_s=wait_timeout_s)
        except BaseException:
            self.refused()
            raise

    def refused(self) -> None:
        self._give_back(keep_last=True)

    def ended(self) -> None:
        self._give_back(keep_last=False)

    def _give_back(self, *, keep_last: bool) -> None:
        with self._lock:
            lent, self._lent = self._lent, None
        if lent is None:
            return
        target, last = lent
        locator = self._core.locator
        locator.use_target(target)
        if keep_last:
            locator.last = last


def observation_tcp(core: CellCore, T_base_target: Matrix4, T_target_tcp: Matrix4) -> Matrix4:
    R_tcp = (T_base_target @ T_target_tcp)[:3, :3]
    cam = observation_camera(T_base_target, core.target_centre_mm,
                             core.config.approach.observe_distance_mm,
                             R_tcp @ core.frames.T_tcp_camera[:3, :3])
    return core.frames.tcp_for_camera(cam)


def locate(core: CellCore, n_frames: int = 1, after_s: float | None = None) -> Located:
    loc = core.locator.locate(n_frames, after_s)
    core.events.publish("locate", {"T_base_target": pose_dict(loc.T_base_target),
                                   "rms_px": float(loc.result.rms_px)})
    return loc


class TargetHidden(Exception):
    """The camera works and its frames do not show the target: a fixed camera's view blocked
    by the arm, a standoff too short for the camera's view, a tool without its plate."""

    def __init__(self, error: CellError) -> None:
        super().__init__(error.message)
        self.error = error


def seen_locate(core: CellCore, n_frames: int = 1, after_s: float | None = None) -> Located:
    """:func:`locate`, a failure other than the camera's raising :class:`TargetHidden`."""
    try:
        return locate(core, n_frames, after_s)
    except CellError as err:
        if err.code in ("camera_lost", "camera_stalled"):
            raise
        raise TargetHidden(err) from err


@dataclass(frozen=True)
class Look:
    """A locate from the still arm and the goal it gives, against the goal the arm went by."""

    located: Located
    goal: Matrix4
    correction_mm: float
    correction_deg: float
    small: bool  # under ``[approach] tolerance_mm`` / ``_deg``: not worth a move

    def cycle(self, n: int) -> Cycle:
        return Cycle(cycle=n, correction_mm=self.correction_mm,
                     correction_deg=self.correction_deg,
                     rms_px=float(self.located.result.rms_px), spread_mm=self.located.spread_mm)

    def closing(self, n: int) -> ClosingCorrection:
        return ClosingCorrection(step=n, correction_mm=self.correction_mm,
                                 correction_deg=self.correction_deg,
                                 rms_px=float(self.located.result.rms_px))


def look_again(core: CellCore, motion: Motion, plan: ApproachPlan, goal: Matrix4, where: str,
               *, may_hide: bool = False) -> Look:
    """The locate-and-correct step every look-and-move takes once the arm has arrived: wait
    ``[approach] settle_s``, locate from frames exposed after that and correct ``goal`` by
    it. ``may_hide``: a target not seen raises :class:`TargetHidden`."""
    ac = core.config.approach
    arrived = time.monotonic()
    if ac.settle_s:
        time.sleep(ac.settle_s)
    motion.raise_if_cancelled(where)
    new = (seen_locate if may_hide else locate)(core, ac.frames_per_locate,
                                                arrived + ac.settle_s)
    new_goal = approach_tcp(new.T_base_target, plan.T_target_tcp, plan.standoff_mm)
    d_mm, d_deg = pose_distance(goal, new_goal)
    return Look(new, new_goal, d_mm, d_deg, d_mm < ac.tolerance_mm and d_deg < ac.tolerance_deg)


def reached(core: CellCore, loc: Located, goal: Matrix4, last: Cycle | ClosingCorrection | None
            ) -> dict[str, Any]:
    """Where the arm stands against ``goal``; the estimated error is what is left unknown:
    the ``last`` correction (estimate noise; none: 0) plus the reach error."""
    at = core.arm.state().T_base_tcp
    reach_mm, reach_deg = pose_distance(at, goal)
    last_mm, last_deg = (0.0, 0.0) if last is None else (last.correction_mm,
                                                         last.correction_deg)
    return {"T_base_target": Pose.from_T(loc.T_base_target), "goal_T_base_tcp": Pose.from_T(goal),
            "reached_T_base_tcp": Pose.from_T(at), "reach_error_mm": reach_mm,
            "reach_error_deg": reach_deg,
            "estimated_error_mm": float(np.hypot(last_mm, reach_mm)),
            "estimated_error_deg": float(np.hypot(last_deg, reach_deg))}


def start_approach(core: CellCore, caller: str, *, standoff_mm: float | None = None,
                   speed_mm_s: float | None = None, T_target_tcp: Matrix4 | None = None,
                   use_last_locate: bool = False, wait: bool = False,
                   wait_timeout_s: float = 120.0,
                   mode: ApproachMode | None = None,
                   recipe: dict[str, Any] | None = None, view: Features | None = None,
                   layout: Target | None = None) -> Job:
    """Start an approach job (``mode`` default: ``[approach] mode``); with ``wait`` return
    when it has ended. ``recipe``: the recipe record the job keeps (cell.features.recipes).
    ``view``: the taught image features an ``ibvs`` approach converges on (required for it).
    ``layout``: the dot layout to look for during this job only (a recipe's target)."""
    ac = core.config.approach
    how = ac.mode if mode is None else mode
    if how not in tuple(ApproachMode):
        raise RefusedError(ErrorCode.invalid_request, f"approach mode must be 'servo', "
                           f"'look_and_move' or 'ibvs', got {mode!r}")
    if how == ApproachMode.ibvs:
        standoff_mm = check_ibvs_request(view, standoff_mm, use_last_locate)
    plan = ApproachPlan(
        standoff_mm=ac.standoff_mm if standoff_mm is None else float(standoff_mm),
        speed_mm_s=ac.speed_mm_s if speed_mm_s is None else float(speed_mm_s),
        accel_mm_s2=min(ac.accel_mm_s2, core.config.limits.max_accel_mm_s2),
        T_target_tcp=ac.T_target_tcp.T() if T_target_tcp is None
        else np.asarray(T_target_tcp, dtype=float))
    params = {"standoff_mm": plan.standoff_mm, "speed_mm_s": plan.speed_mm_s,
              "T_target_tcp": pose_dict(plan.T_target_tcp), "use_last_locate": use_last_locate,
              "mode": how}
    if recipe is not None:
        params["recipe"] = recipe
    first: list[Located] = []
    seen: dict[str, Any] = {}  # how a fixed camera's pose was had (live or before occlusion)
    lent = JobLayout(core, layout)

    def checks(motion: Motion) -> None:
        check_standoff(plan.standoff_mm)
        core.arm.guard.check_speed(plan.speed_mm_s, plan.accel_mm_s2)
        st = core.arm.ready_state()
        if not core.camera.is_connected:
            raise UnavailableError(ErrorCode.camera_lost, "the camera is lost: approach needs it "
                                   "(jogging is still possible)")
        # the servo re-estimates from every frame: one frame to start from is enough
        n_frames = 1 if how in (ApproachMode.servo, ApproachMode.ibvs) else ac.frames_per_locate
        began_s = time.monotonic()
        if use_last_locate:
            loc = _last_locate(core)
        elif how == ApproachMode.ibvs and core.frames.is_fixed:
            assert view is not None
            loc = tool_plate_locate(core, plan.T_target_tcp)
            core.arm.guard.check_goal(st.T_base_tcp, IbvsMount.of(
                core.frames, view, core.locator.target.points_mm).goal(
                    loc.T_base_target, loc.T_base_tcp, plan.T_target_tcp), "IBVS goal estimate",
                st)
            first.append(loc)
            return
        elif core.frames.is_fixed:
            loc = _fixed_locate(core, n_frames, seen)
        else:
            loc = locate(core, n_frames)
        goal = approach_tcp(loc.T_base_target, plan.T_target_tcp, plan.standoff_mm)
        streamed = how in (ApproachMode.servo, ApproachMode.ibvs)
        if streamed or core.frames.is_fixed:  # straight at the goal: checked
            core.arm.guard.check_goal(st.T_base_tcp, goal, "approach goal", st)
        else:  # both goals are checked now (reach too), so that a refusal moves nothing
            T_obs = observation_tcp(core, loc.T_base_target, plan.T_target_tcp)
            core.arm.guard.check_goal(st.T_base_tcp, T_obs, "observation pose", st)
            core.arm.guard.check_goal(T_obs, goal, "approach goal", st)
        first.append(loc)
        seen["first_locate_s"] = round(time.monotonic() - began_s, 4)

    def work(job_id: str, motion: Motion) -> LookAndMoveApproach | ServoApproach | IbvsApproach:
        try:
            return run(job_id, motion)
        finally:
            lent.ended()

    def run(job_id: str, motion: Motion) -> LookAndMoveApproach | ServoApproach | IbvsApproach:
        loc = first[0]
        if how == ApproachMode.ibvs:
            assert view is not None
            start: dict[str, Any] = {"first_locate_s": seen.get("first_locate_s"),
                                     "consistency": first_consistency(core, loc)}
            return IbvsApproach(mode=ApproachMode.ibvs, **ClosedLoop(core, job_id, motion, ImageLaw(
                core, view, plan.T_target_tcp, "approach")).run(loc),
                estimated_error_basis=ERROR_BASIS["ibvs"], **start)
        return pose_approach(core, job_id, motion, loc, plan, how, seen)

    return lent.start_job("approach", caller, params, work, checks, wait=wait,
                          wait_timeout_s=wait_timeout_s)


def first_consistency(core: CellCore, loc: Located) -> Consistency:
    return Consistency.model_validate(consistency(
        [("initial locate", loc)], core.target_centre_mm, target_at_rest=False))


def pose_approach(core: CellCore, job_id: str, motion: Motion, loc: Located, plan: ApproachPlan,
                  how: ApproachMode, seen: dict[str, Any]
                  ) -> LookAndMoveApproach | ServoApproach:
    """Approach ``plan``'s goal from the first locate ``loc`` by pose (look-and-move or the
    servo; a fixed camera's look-and-move corrects at the goal); ``seen``: how the first
    locate was had (``first_locate_s``, a fixed camera's pose source)."""
    start: dict[str, Any] = {"first_locate_s": seen.get("first_locate_s")}
    if how == ApproachMode.look_and_move and not core.frames.is_fixed:
        return look_and_move(core, job_id, motion, loc, plan, start)
    start["consistency"] = first_consistency(core, loc)
    if how == ApproachMode.servo:
        return servo_approach(core, job_id, motion, loc, plan, seen, start)
    return fixed_look_and_move(core, job_id, motion, loc, plan, seen, start)


def check_ibvs_request(view: Features | None, standoff_mm: float | None,
                       use_last_locate: bool = False) -> float:
    """An IBVS job converges on a taught view: it needs one, and it goes to that view itself
    (a standoff would be a view nobody showed). Returns the standoff (0)."""
    if view is None:
        raise LimitError(ErrorCode.taught_without_view, "mode 'ibvs' needs a pose taught with its "
                         "view (give `taught`; poses taught before views were recorded serve "
                         "servo and look_and_move only: teach it again for ibvs)")
    if standoff_mm not in (None, 0, 0.0):
        raise LimitError(ErrorCode.invalid_standoff, "mode 'ibvs' goes to the taught view itself: "
                         f"standoff_mm must be 0 or absent, got {standoff_mm}")
    if use_last_locate:
        raise LimitError(ErrorCode.invalid_request, "mode 'ibvs' servos on live frames; "
                         "use_last_locate does not apply")
    return 0.0


TOOL_PLATE_MM = 10.0  # the plate seen must sit this close to where it was on the tool when
TOOL_PLATE_DEG = 3.0  # taught (hand-eye errors move it by tenths of a millimetre)


def tool_plate_locate(core: CellCore, T_plate_tcp: Matrix4) -> Located:
    """A fixed camera's IBVS drives a dot plate clamped to the tool: locate it and check that
    it is one, i.e. that the plate seen sits where the taught view had it relative to the TCP
    (``T_plate_tcp``, the taught ``T_target_tcp``). A plate on the table, a plate moved on
    the tool, or none in view: ``no_tool_plate``, nothing moves."""
    try:
        loc = seen_locate(core, 1)
    except TargetHidden as hidden:
        raise RefusedError(ErrorCode.no_tool_plate, "mode 'ibvs' with a fixed camera drives the "
                           "dot plate clamped to the tool, and the camera sees no plate: "
                           f"{hidden}") from hidden.error
    d_mm, d_deg = pose_distance(invert_T(loc.T_base_target) @ loc.T_base_tcp, T_plate_tcp)
    if d_mm > TOOL_PLATE_MM or d_deg > TOOL_PLATE_DEG:
        raise RefusedError(ErrorCode.no_tool_plate, "mode 'ibvs' with a fixed camera drives the "
                           "dot plate clamped to the tool; the plate in view is "
                           f"{d_mm:.1f} mm / {d_deg:.1f} deg from where the taught view had it "
                           f"relative to the TCP (limit {TOOL_PLATE_MM:g} mm / "
                           f"{TOOL_PLATE_DEG:g} deg): it is not on the tool, or it moved there "
                           "(teach the view again)")
    return loc


def _last_locate(core: CellCore) -> Located:
    loc = core.locator.last
    if loc is None:
        raise RefusedError(ErrorCode.stale_pose, "no target has been located yet")
    age = time.monotonic() - loc.frame_timestamp_s
    limit = core.config.limits.max_pose_age_s
    if age > limit:
        raise RefusedError(ErrorCode.stale_pose, f"the last located pose is {age:.1f} s old (limit "
                           f"{limit} s); locate again")
    return loc


def _fixed_locate(core: CellCore, n_frames: int, seen: dict[str, Any]) -> Located:
    """Locate with a fixed camera; when the target is not found, the arm may be standing
    between the camera and the target: then the last pose seen (before the arm entered the
    view) is used, and the result says so. Without an earlier pose the error stands."""
    try:
        loc = seen_locate(core, n_frames)
    except TargetHidden as hidden:
        last = core.locator.last
        if last is None:
            raise hidden.error from None
        seen.update(pose_source="last_seen", occluded=True, reason=str(hidden),
                    pose_age_s=time.monotonic() - last.frame_timestamp_s)
        return last
    seen.update(pose_source="live", occluded=False)
    return loc


def fixed_look_and_move(core: CellCore, job_id: str, motion: Motion, loc: Located,
                        plan: ApproachPlan, seen: dict[str, Any], start: dict[str, Any]
                        ) -> LookAndMoveApproach:
    """Look-and-move with a fixed camera: no observation pose (the camera does not move with
    the arm); straight to the goal, then, while the camera still sees the target past the
    arm, locate again at rest and correct until under the tolerance. Once the arm hides the
    target the goal stays the one from the last pose seen, and the result says so."""
    ac = core.config.approach
    cycles: list[Cycle] = []
    converged = occluded_at_goal = False
    goal = approach_tcp(loc.T_base_target, plan.T_target_tcp, plan.standoff_mm)
    for cycle in range(1, ac.max_cycles + 1):
        core.runner.progress(job_id, {"phase": "move", "cycle": cycle, "cycles": _rows(cycles)})
        core.arm.move_linear(goal, plan.speed_mm_s, plan.accel_mm_s2, what="approach goal")
        try:
            look = look_again(core, motion, plan, goal, "at the approach goal", may_hide=True)
        except TargetHidden as hidden:
            occluded_at_goal = True
            seen.setdefault("reason", str(hidden))
            break
        cycles.append(look.cycle(cycle))
        loc, goal, converged = look.located, look.goal, look.small
        if converged:
            break
    if not converged:
        core.arm.move_linear(goal, plan.speed_mm_s, plan.accel_mm_s2, what="approach goal")
    return LookAndMoveApproach(
        mode=ApproachMode.look_and_move, camera_mount="fixed", converged=converged,
        cycles=cycles,
        # the pose the goal came from: "live" (seen at the start or at the goal) or
        # "last_seen" (the arm hid the target: the last pose before it entered the view)
        pose_source=seen.get("pose_source", "live"),
        occluded=bool(seen.get("occluded", False)) or occluded_at_goal,
        occluded_at_goal=occluded_at_goal, pose_age_s=seen.get("pose_age_s"),
        occlusion_reason=seen.get("reason"),
        **reached(core, loc, goal, cycles[-1] if cycles else None),
        estimated_error_basis=ERROR_BASIS["fixed"], **start)


def _close_at_goal(core: CellCore, motion: Motion, plan: ApproachPlan, goal: Matrix4
                   ) -> tuple[list[ClosingStep], Matrix4]:
    """Locate again at the goal and correct until under the tolerance (up to ``max_cycles``
    moves): the move from the observation pose to the goal runs open-loop over a few hundred
    millimetres, where an arm's kinematic error changes by tenths of a millimetre (an arm
    without its factory calibration); the short corrections from views at the goal do not
    carry it. A goal the camera does not see the target from (a standoff too short for its
    view) keeps the observation pose's goal, and the steps say why. Returns the steps and the
    goal the arm stands at."""
    steps: list[ClosingStep] = []
    for step in range(1, core.config.approach.max_cycles + 1):
        try:
            look = look_again(core, motion, plan, goal, "at the approach goal", may_hide=True)
        except TargetHidden as hidden:
            steps.append(ClosingNotSeen(step=step, not_seen=str(hidden)))
            break
        steps.append(look.closing(step))
        if look.small:
            break
        goal = look.goal
        core.arm.move_linear(goal, plan.speed_mm_s, plan.accel_mm_s2, what="approach goal")
    return steps, goal


def servo_approach(core: CellCore, job_id: str, motion: Motion, loc: Located,
                   plan: ApproachPlan, seen: dict[str, Any], start: dict[str, Any]
                   ) -> ServoApproach:
    """The servo until converged. An approach converges only on the mean of ``[servo]
    rest_frames`` poses of the target at rest, seen from within 0.1 mm of where the arm
    stops: a closing look of a few still frames after it (as look-and-move ends) would
    replace that mean with a noisier one (3 frames: 0.065 mm RMS at the TCP from home,
    against 0.02 mm for 30; docs/performance.md)."""
    out = ClosedLoop(core, job_id, motion, PositionLaw(core, ServoGoal(
        plan.T_target_tcp, plan.standoff_mm), "approach")).run(loc)
    basis = "fixed" if core.frames.is_fixed else "servo"
    if seen.get("pose_source") == "last_seen":  # a fixed camera, hidden at the start
        out.update(start_pose_source="last_seen", occluded=True,
                   occlusion_reason=out.get("occlusion_reason") or seen.get("reason"))
    return ServoApproach(mode=ApproachMode.servo, **out, estimated_error_basis=ERROR_BASIS[basis],
                         **start)


# How each approach estimates its own error, and what that estimate cannot see.
ERROR_BASIS: dict[str, ErrorBasis] = {
    "look_and_move": ErrorBasis(
        frame="base",
        text="the last correction of the goal in the base frame (seen from the goal, or "
             "else two locates from the same observation pose) plus the reach error; both "
             "go through the hand-eye calibration and the intrinsics, so their error is "
             "invisible here: see consistency"),
    "fixed": ErrorBasis(
        frame="base",
        text="the last correction of the goal in the base frame (a fixed camera seeing the "
             "target at the goal) plus the reach error; both go through T_base_camera, so "
             "its error is invisible here"),
    "servo": ErrorBasis(
        frame="camera",
        text="the TCP against the goal the camera sees from where it stands (a target at "
             "rest: the mean of its poses from this viewpoint, plus twice the mean's standard "
             "error), plus what the view resolves at the TCP; a hand-eye or intrinsics error "
             "is invisible here"),
    "ibvs": ErrorBasis(
        frame="image",
        text="the TCP motion the converged window's mean view still asks for (the dots' "
             "image features against the taught view's) plus what the two views resolve at "
             "the TCP: their noise over the frames each averages and the dots' centre bias, "
             "through the interaction matrix; a mount error between teaching and now is "
             "invisible here"),
}


def _rows(rows: list[Cycle]) -> list[dict[str, Any]]:
    """Rows for a job's progress (plain JSON)."""
    return [row.json_dict() for row in rows]


def checked(core: CellCore, job_id: str, seen: list[tuple[str, Located]]) -> dict[str, Any]:
    """The consistency block of an approach's locates; an inconsistency is logged and
    published (``consistency`` events) so the operator learns of it while the job succeeds."""
    block = consistency(seen, core.target_centre_mm)
    if block["verdict"] == "inconsistent":
        log.warning("approach job %s: %s", job_id, " ".join(block["findings"]))
        core.events.publish("consistency", {"job_id": job_id, "verdict": block["verdict"],
                                            "codes": block["codes"],
                                            "findings": block["findings"]})
    return block


def look_and_move(core: CellCore, job_id: str, motion: Motion, loc: Located,
                  plan: ApproachPlan, start: dict[str, Any]) -> LookAndMoveApproach:
    ac = core.config.approach
    cycles: list[Cycle] = []
    converged = False
    goal = approach_tcp(loc.T_base_target, plan.T_target_tcp, plan.standoff_mm)
    seen: list[tuple[str, Located]] = [("initial locate", loc)]
    for cycle in range(1, ac.max_cycles + 1):
        core.runner.progress(job_id, {"phase": "observe", "cycle": cycle, "cycles": _rows(cycles)})
        T_obs = observation_tcp(core, loc.T_base_target, plan.T_target_tcp)
        core.arm.move_linear(T_obs, plan.speed_mm_s, plan.accel_mm_s2, what="observation pose")
        core.runner.progress(job_id, {"phase": "locate", "cycle": cycle, "cycles": _rows(cycles)})
        look = look_again(core, motion, plan, goal, "at the observation pose")
        cycles.append(look.cycle(cycle))
        seen.append((f"cycle {cycle}", look.located))
        loc, goal, converged = look.located, look.goal, look.small
        if converged:
            break
        motion.raise_if_cancelled("between cycles")
    core.runner.progress(job_id, {"phase": "final", "cycle": len(cycles), "cycles": _rows(cycles)})
    core.arm.move_linear(goal, plan.speed_mm_s, plan.accel_mm_s2, what="approach goal")
    closing, goal = _close_at_goal(core, motion, plan, goal)
    last = closing[-1] if closing and isinstance(closing[-1], ClosingCorrection) else cycles[-1]
    return LookAndMoveApproach(
        mode=ApproachMode.look_and_move, converged=converged, cycles=cycles, closing=closing,
        **reached(core, loc, goal, last), estimated_error_basis=ERROR_BASIS["look_and_move"],
        consistency=Consistency.model_validate(checked(core, job_id, seen)), **start)
