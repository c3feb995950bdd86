"""Approach: by look-and-move (observe, locate, correct, repeat, then the final move), by
closed-loop servoing (``mode="servo"``, :mod:`cell.actions.servo`) or by image-based servoing to a
taught view (``mode="ibvs"``, :mod:`cell.actions.ibvs_run`).

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
from cell.actions.ibvs import Features
from cell.actions.ibvs_mount import IbvsMount
from cell.actions.ibvs_run import IbvsRun
from cell.actions.servo import ServoGoal, ServoRun
from cell.core import CellCore
from cell.error_codes import ErrorCode
from cell.errors import CellError, LimitError, RefusedError, UnavailableError
from cell.jobs.runner import Work
from cell.jobs.store import Job
from cell.motion.guard import Motion
from cell.results.modes import ApproachMode
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
    if how == "ibvs":
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
        n_frames = 1 if how in ("servo", "ibvs") else ac.frames_per_locate
        began_s = time.monotonic()
        if use_last_locate:
            loc = _last_locate(core)
        elif how == "ibvs" and core.frames.is_fixed:
            assert view is not None
            loc = tool_plate_locate(core, plan.T_target_tcp)
            core.arm.guard.check_goal(st.T_base_tcp, IbvsMount.of(
                core.frames, view, core.locator.target.points_mm).goal(
                    loc.T_base_target, loc.T_base_tcp, plan.T_target_tcp), "IBVS goal estimate")
            first.append(loc)
            return
        elif core.frames.is_fixed:
            loc = _fixed_locate(core, n_frames, seen)
        else:
            loc = locate(core, n_frames)
        goal = approach_tcp(loc.T_base_target, plan.T_target_tcp, plan.standoff_mm)
        if how in ("servo", "ibvs") or core.frames.is_fixed:  # straight at the goal: checked
            core.arm.guard.check_goal(st.T_base_tcp, goal, "approach goal")
        else:  # both goals are checked now, so that a refusal moves nothing
            T_obs = observation_tcp(core, loc.T_base_target, plan.T_target_tcp)
            core.arm.guard.check_goal(st.T_base_tcp, T_obs, "observation pose")
            core.arm.guard.check_goal(T_obs, goal, "approach goal")
        first.append(loc)
        seen["first_locate_s"] = round(time.monotonic() - began_s, 4)

    def work(job_id: str, motion: Motion) -> dict[str, Any]:
        try:
            result = run(job_id, motion)
        finally:
            lent.ended()
        result.setdefault("first_locate_s", seen.get("first_locate_s"))
        basis = ERROR_BASIS.get("fixed" if result.get("camera_mount") == "fixed"
                                else str(result.get("mode")))
        if basis is not None:
            result.setdefault("estimated_error_basis", basis)
        if "consistency" not in result:  # servo, IBVS, a fixed camera: the first locate's
            result["consistency"] = consistency([("initial locate", first[0])],
                                                core.target_centre_mm, target_at_rest=False)
        return result

    def run(job_id: str, motion: Motion) -> dict[str, Any]:
        if how == "ibvs":
            assert view is not None
            return IbvsRun(core, job_id, motion, view, plan.T_target_tcp,
                           "approach").run(first[0])
        if how == "servo":
            run = ServoRun(core, job_id, motion, ServoGoal(plan.T_target_tcp, plan.standoff_mm),
                           "approach", first=first[0])
            out = run.run()
            if not core.frames.is_fixed and _at_rest(out):
                _close_servo(core, motion, plan, out)
            if seen.get("pose_source") == "last_seen":  # a fixed camera, hidden at the start
                out.update(start_pose_source="last_seen", occluded=True,
                           occlusion_reason=out.get("occlusion_reason") or seen.get("reason"))
            return out
        if core.frames.is_fixed:
            return fixed_look_and_move(core, job_id, motion, first[0], plan, seen)
        return look_and_move(core, job_id, motion, first[0], plan)

    return lent.start_job("approach", caller, params, work, checks, wait=wait,
                          wait_timeout_s=wait_timeout_s)


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
        loc = locate(core, 1)
    except CellError as err:
        if err.code in ("camera_lost", "camera_stalled"):
            raise
        raise RefusedError(ErrorCode.no_tool_plate, "mode 'ibvs' with a fixed camera drives the "
                           "dot plate clamped to the tool, and the camera sees no plate: "
                           f"{err.message}") from err
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
        loc = locate(core, n_frames)
    except CellError as err:
        last = core.locator.last
        if last is None or err.code in ("camera_lost", "camera_stalled"):
            raise
        seen.update(pose_source="last_seen", occluded=True, reason=err.message,
                    pose_age_s=time.monotonic() - last.frame_timestamp_s)
        return last
    seen.update(pose_source="live", occluded=False)
    return loc


def fixed_look_and_move(core: CellCore, job_id: str, motion: Motion, loc: Located,
                        plan: ApproachPlan, seen: dict[str, Any]) -> dict[str, Any]:
    """Look-and-move with a fixed camera: no observation pose (the camera does not move with
    the arm); straight to the goal, then, while the camera still sees the target past the
    arm, locate again at rest and correct until under the tolerance. Once the arm hides the
    target the goal stays the one from the last pose seen, and the result says so."""
    ac = core.config.approach
    arm = core.arm
    cycles: list[dict[str, Any]] = []
    converged = False
    goal = approach_tcp(loc.T_base_target, plan.T_target_tcp, plan.standoff_mm)
    occluded_at_goal = False
    for cycle in range(1, ac.max_cycles + 1):
        core.runner.progress(job_id, {"phase": "move", "cycle": cycle, "cycles": cycles})
        arm.move_linear(goal, plan.speed_mm_s, plan.accel_mm_s2, what="approach goal")
        arrived = time.monotonic()
        if ac.settle_s:
            time.sleep(ac.settle_s)
        motion.raise_if_cancelled("at the approach goal")
        try:
            new = locate(core, ac.frames_per_locate, after_s=arrived + ac.settle_s)
        except CellError as err:
            if err.code in ("camera_lost", "camera_stalled"):
                raise
            occluded_at_goal = True
            seen.setdefault("reason", err.message)
            break
        new_goal = approach_tcp(new.T_base_target, plan.T_target_tcp, plan.standoff_mm)
        d_mm, d_deg = pose_distance(goal, new_goal)
        cycles.append({"cycle": cycle, "correction_mm": d_mm, "correction_deg": d_deg,
                       "rms_px": float(new.result.rms_px), "spread_mm": new.spread_mm})
        loc, goal = new, new_goal
        if d_mm < ac.tolerance_mm and d_deg < ac.tolerance_deg:
            converged = True
            break
    if not converged:
        arm.move_linear(goal, plan.speed_mm_s, plan.accel_mm_s2, what="approach goal")
    reached = arm.state().T_base_tcp
    reach_mm, reach_deg = pose_distance(reached, goal)
    last_mm = cycles[-1]["correction_mm"] if cycles else 0.0
    last_deg = cycles[-1]["correction_deg"] if cycles else 0.0
    return {
        "mode": "look_and_move",
        "camera_mount": "fixed",
        "converged": converged,
        "cycles": cycles,
        # the pose the goal came from: "live" (seen at the start or at the goal) or
        # "last_seen" (the arm hid the target: the last pose before it entered the view)
        "pose_source": seen.get("pose_source", "live"),
        "occluded": bool(seen.get("occluded", False)) or occluded_at_goal,
        "occluded_at_goal": occluded_at_goal,
        "pose_age_s": seen.get("pose_age_s"),
        "occlusion_reason": seen.get("reason"),
        "T_base_target": pose_dict(loc.T_base_target),
        "goal_T_base_tcp": pose_dict(goal),
        "reached_T_base_tcp": pose_dict(reached),
        "reach_error_mm": reach_mm,
        "reach_error_deg": reach_deg,
        "estimated_error_mm": float(np.hypot(last_mm, reach_mm)),
        "estimated_error_deg": float(np.hypot(last_deg, reach_deg)),
    }


def _close_at_goal(core: CellCore, motion: Motion, plan: ApproachPlan, goal: Matrix4
                   ) -> tuple[list[dict[str, Any]], Matrix4]:
    """Locate again at the goal and correct until under the tolerance (up to ``max_cycles``
    moves): the move from the observation pose to the goal runs open-loop over a few hundred
    millimetres, where an arm's kinematic error changes by tenths of a millimetre (an arm
    without its factory calibration); the short corrections from views at the goal do not
    carry it. A goal the camera does not see the target from (a standoff too short for its
    view) keeps the observation pose's goal, and the steps say why. Returns the steps and the
    goal the arm stands at."""
    ac = core.config.approach
    steps: list[dict[str, Any]] = []
    for step in range(1, ac.max_cycles + 1):
        arrived = time.monotonic()
        if ac.settle_s:
            time.sleep(ac.settle_s)
        motion.raise_if_cancelled("at the approach goal")
        try:
            seen = locate(core, ac.frames_per_locate, after_s=arrived + ac.settle_s)
        except CellError as err:
            if err.code in ("camera_lost", "camera_stalled"):
                raise
            steps.append({"step": step, "not_seen": err.message})
            break
        new_goal = approach_tcp(seen.T_base_target, plan.T_target_tcp, plan.standoff_mm)
        d_mm, d_deg = pose_distance(goal, new_goal)
        steps.append({"step": step, "correction_mm": d_mm, "correction_deg": d_deg,
                      "rms_px": float(seen.result.rms_px)})
        if d_mm < ac.tolerance_mm and d_deg < ac.tolerance_deg:
            break
        goal = new_goal
        core.arm.move_linear(goal, plan.speed_mm_s, plan.accel_mm_s2, what="approach goal")
    return steps, goal


# A servo approach's target counts as at rest below this filtered speed: then the arm, stopped
# at convergence, closes on still views as look-and-move does.
AT_REST_MM_S = 1.0


def _at_rest(servo_result: dict[str, Any]) -> bool:
    velocity = servo_result.get("target_velocity_mm_s")
    return velocity is not None and float(np.linalg.norm(velocity)) < AT_REST_MM_S


def _close_servo(core: CellCore, motion: Motion, plan: ApproachPlan,
                 out: dict[str, Any]) -> None:
    """The servo stops on the filtered estimate of a moving view (blur, latency), which
    spreads its end about the goal (0.03-0.14 mm measured in the realistic world); with the
    target at rest the stopped arm closes on still views (:func:`_close_at_goal`). The
    result's ``closing`` lists the steps and its estimate becomes the last correction."""
    here = core.arm.state().T_base_tcp
    steps, goal = _close_at_goal(core, motion, plan, here)
    out["closing"] = steps
    if steps and "correction_mm" in steps[-1]:
        reached = core.arm.state().T_base_tcp
        out.update(goal_T_base_tcp=pose_dict(goal), reached_T_base_tcp=pose_dict(reached),
                   estimated_error_mm=steps[-1]["correction_mm"],
                   estimated_error_deg=steps[-1]["correction_deg"],
                   estimated_error_basis=ERROR_BASIS["servo_closed"])


# How each approach estimates its own error, and what that estimate cannot see.
ERROR_BASIS: dict[str, dict[str, str]] = {
    "look_and_move": {
        "frame": "base",
        "text": "the last correction of the goal in the base frame (seen from the goal, or "
                "else two locates from the same observation pose) plus the reach error; both "
                "go through the hand-eye calibration and the intrinsics, so their error is "
                "invisible here: see consistency"},
    "fixed": {
        "frame": "base",
        "text": "the last correction of the goal in the base frame (a fixed camera seeing the "
                "target at the goal) plus the reach error; both go through T_base_camera, so "
                "its error is invisible here"},
    "servo_closed": {
        "frame": "base",
        "text": "the last correction of the goal in the base frame, seen from still views at "
                "the goal after the servo stopped (the target at rest); it goes through the "
                "hand-eye calibration and the intrinsics, so their error is invisible here"},
    "servo": {
        "frame": "camera",
        "text": "the TCP against the goal the camera sees from where it stands, i.e. the "
                "target in the camera frame; a hand-eye or intrinsics error is invisible here"},
    "ibvs": {
        "frame": "image",
        "text": "the dots' image features against the taught view's; the pose figures are the "
                "camera frame's; a mount error between teaching and now is invisible here"},
}


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
                  plan: ApproachPlan) -> dict[str, Any]:
    ac = core.config.approach
    arm = core.arm
    cycles: list[dict[str, Any]] = []
    converged = False
    goal = approach_tcp(loc.T_base_target, plan.T_target_tcp, plan.standoff_mm)
    seen: list[tuple[str, Located]] = [("initial locate", loc)]
    for cycle in range(1, ac.max_cycles + 1):
        core.runner.progress(job_id, {"phase": "observe", "cycle": cycle, "cycles": cycles})
        T_obs = observation_tcp(core, loc.T_base_target, plan.T_target_tcp)
        arm.move_linear(T_obs, plan.speed_mm_s, plan.accel_mm_s2, what="observation pose")
        arrived = time.monotonic()
        if ac.settle_s:
            time.sleep(ac.settle_s)
        motion.raise_if_cancelled("at the observation pose")
        core.runner.progress(job_id, {"phase": "locate", "cycle": cycle, "cycles": cycles})
        new = locate(core, ac.frames_per_locate, after_s=arrived + ac.settle_s)
        new_goal = approach_tcp(new.T_base_target, plan.T_target_tcp, plan.standoff_mm)
        d_mm, d_deg = pose_distance(goal, new_goal)
        cycles.append({"cycle": cycle, "correction_mm": d_mm, "correction_deg": d_deg,
                       "rms_px": float(new.result.rms_px), "spread_mm": new.spread_mm})
        seen.append((f"cycle {cycle}", new))
        loc, goal = new, new_goal
        if d_mm < ac.tolerance_mm and d_deg < ac.tolerance_deg:
            converged = True
            break
        motion.raise_if_cancelled("between cycles")
    core.runner.progress(job_id, {"phase": "final", "cycle": len(cycles), "cycles": cycles})
    arm.move_linear(goal, plan.speed_mm_s, plan.accel_mm_s2, what="approach goal")
    closing, goal = _close_at_goal(core, motion, plan, goal)
    reached = arm.state().T_base_tcp
    reach_mm, reach_deg = pose_distance(reached, goal)
    last = closing[-1] if closing and "correction_mm" in closing[-1] else cycles[-1]
    return {
        "mode": "look_and_move",
        "converged": converged,
        "cycles": cycles,
        "closing": closing,
        "T_base_target": pose_dict(loc.T_base_target),
        "goal_T_base_tcp": pose_dict(goal),
        "reached_T_base_tcp": pose_dict(reached),
        "reach_error_mm": reach_mm,
        "reach_error_deg": reach_deg,
        # what is left unknown: the last correction (estimate noise) plus the reach error
        "estimated_error_mm": float(np.hypot(last["correction_mm"], reach_mm)),
        "estimated_error_deg": float(np.hypot(last["correction_deg"], reach_deg)),
        "estimated_error_basis": ERROR_BASIS["look_and_move"],
        "consistency": checked(core, job_id, seen),
    }
