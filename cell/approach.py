"""Approach: by look-and-move (observe, locate, correct, repeat, then the final move) or by
closed-loop servoing (``mode="servo"``, :mod:`cell.servo`).

The goal is ``T_base_target @ T_target_tcp @ translate(0, 0, -standoff_mm)``. The arm first
goes to an observation pose in front of the target with the goal's orientation (so the final
move is a pure translation and every cycle sees the target from the same viewpoint), locates
again from frames exposed after it stopped, and repeats until the correction is under the
tolerance or the cycle limit; every cycle's correction and the final estimated error are in
the job's result. Every goal is checked before the job starts, so a refusal moves nothing.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Any, Literal

import numpy as np
from numpy.typing import NDArray

from cell.core import CellCore
from cell.frames import approach_tcp, observation_camera
from cell.jobs import Job
from cell.locate import Located
from cell.motion import Motion
from cell.safety import LimitError, RefusedError, UnavailableError
from cell.servo import ServoGoal, ServoRun
from estimator.transforms import pose_dict, pose_distance

Matrix4 = NDArray[np.float64]


@dataclass(frozen=True)
class ApproachPlan:
    standoff_mm: float
    speed_mm_s: float
    accel_mm_s2: float
    T_target_tcp: Matrix4


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
                   mode: Literal["servo", "look_and_move"] | None = None,
                   recipe: dict[str, Any] | None = None) -> Job:
    """Start an approach job (``mode`` default: ``[approach] mode``); with ``wait`` return
    when it has ended. ``recipe``: the recipe record the job keeps (cell.recipes)."""
    ac = core.config.approach
    how = ac.mode if mode is None else mode
    if how not in ("servo", "look_and_move"):
        raise RefusedError("invalid_request", f"approach mode must be 'servo' or "
                           f"'look_and_move', got {mode!r}")
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

    def check(motion: Motion) -> None:
        if not np.isfinite(plan.standoff_mm) or plan.standoff_mm < 0:
            raise LimitError("invalid_standoff", "standoff_mm must be a number >= 0")
        core.arm.guard.check_speed(plan.speed_mm_s, plan.accel_mm_s2)
        st = core.arm.ready_state()
        if not core.camera.is_connected:
            raise UnavailableError("camera_lost", "the camera is lost: approach needs it "
                                   "(jogging is still possible)")
        # the servo re-estimates from every frame: one frame to start from is enough
        n_frames = 1 if how == "servo" else ac.frames_per_locate
        loc = _last_locate(core) if use_last_locate else locate(core, n_frames)
        goal = approach_tcp(loc.T_base_target, plan.T_target_tcp, plan.standoff_mm)
        if how == "servo":  # the servo moves straight at the goal: that path is checked
            core.arm.guard.check_goal(st.T_base_tcp, goal, "approach goal")
        else:  # both goals are checked now, so that a refusal moves nothing
            T_obs = observation_tcp(core, loc.T_base_target, plan.T_target_tcp)
            core.arm.guard.check_goal(st.T_base_tcp, T_obs, "observation pose")
            core.arm.guard.check_goal(T_obs, goal, "approach goal")
        first.append(loc)

    def work(job_id: str, motion: Motion) -> dict[str, Any]:
        if how == "servo":
            run = ServoRun(core, job_id, motion, ServoGoal(plan.T_target_tcp, plan.standoff_mm),
                           "approach", first=first[0])
            return run.run()
        return look_and_move(core, job_id, motion, first[0], plan)

    return core.runner.start("approach", caller, params, work, check=check, needs_camera=True,
                             wait=wait, wait_timeout_s=wait_timeout_s)


def _last_locate(core: CellCore) -> Located:
    loc = core.locator.last
    if loc is None:
        raise RefusedError("stale_pose", "no target has been located yet")
    age = time.monotonic() - loc.frame_timestamp_s
    limit = core.config.limits.max_pose_age_s
    if age > limit:
        raise RefusedError("stale_pose", f"the last located pose is {age:.1f} s old (limit "
                           f"{limit} s); locate again")
    return loc


def look_and_move(core: CellCore, job_id: str, motion: Motion, loc: Located,
                  plan: ApproachPlan) -> dict[str, Any]:
    ac = core.config.approach
    arm = core.arm
    cycles: list[dict[str, Any]] = []
    converged = False
    goal = approach_tcp(loc.T_base_target, plan.T_target_tcp, plan.standoff_mm)
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
        loc, goal = new, new_goal
        if d_mm < ac.tolerance_mm and d_deg < ac.tolerance_deg:
            converged = True
            break
        motion.raise_if_cancelled("between cycles")
    core.runner.progress(job_id, {"phase": "final", "cycle": len(cycles), "cycles": cycles})
    arm.move_linear(goal, plan.speed_mm_s, plan.accel_mm_s2, what="approach goal")
    reached = arm.state().T_base_tcp
    reach_mm, reach_deg = pose_distance(reached, goal)
    last = cycles[-1]
    return {
        "mode": "look_and_move",
        "converged": converged,
        "cycles": cycles,
        "T_base_target": pose_dict(loc.T_base_target),
        "goal_T_base_tcp": pose_dict(goal),
        "reached_T_base_tcp": pose_dict(reached),
        "reach_error_mm": reach_mm,
        "reach_error_deg": reach_deg,
        # what is left unknown: the last correction (estimate noise) plus the reach error
        "estimated_error_mm": float(np.hypot(last["correction_mm"], reach_mm)),
        "estimated_error_deg": float(np.hypot(last["correction_deg"], reach_deg)),
    }
