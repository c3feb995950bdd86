"""The position-based law (PBVS, approach mode ``"servo"`` and tracking): the target's pose in
the base frame, filtered, and the TCP's goal at a standoff from it.

A frame's pose must pass a validation gate (near the filter's prediction, widening with the
time since the last pose let in) before it corrects the constant-velocity filter
(:mod:`cell.servoing.target_filter`). Each tick predicts the target *now*, makes the goal
``T_base_target @ T_target_tcp @ translate(0, 0, -standoff)`` and takes the twist of
:mod:`cell.servoing.servo_law` (feed-forward of the goal's velocity plus an exponential
approach; tracking adds an integral term near the goal). Converged: the error under ``[servo]
tolerance_mm`` / ``tolerance_deg`` on ``converge_frames`` consecutive frames, once the goal
comes from the mean of ``rest_frames`` poses of the target at rest.

A fixed camera: the target pose has no flange in its chain (:class:`cell.vision.frames.
CellFrames`), so the law is the same. Near the goal the arm itself hides the target; an
approach then goes on to the goal of the last pose seen, held still (as the fixed look-and-move
does), and its result says so (``pose_source = "last_seen"``, ``occluded``, ``pose_age_s``).
The target must not move meanwhile: tracking still ends ``target_lost``, and so does a stalled
camera (no frames examined).
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from cell.core import CellCore
from cell.error_codes import ErrorCode
from cell.errors import RefusedError
from cell.motion.limits import linear_path
from cell.results import Pose
from cell.servoing.clock import TwistClock
from cell.servoing.law import Law, Loop, LoopMode, Reading, StreamCaps, Tick, Unusable
from cell.servoing.record import FrameStats, ms_stats
from cell.servoing.rest_mean import RestMean
from cell.servoing.servo_law import LawParams, goal_velocity, integrate, pbvs_twist, pose_error
from cell.servoing.target_filter import ConstantVelocityFilter, TargetEstimate
from cell.servoing.view_bound import Resolution, pose_resolution
from cell.vision.frames import approach_tcp
from cell.vision.locate import Located
from drivers.arm import ArmState
from estimator.transforms import invert_T, pose_distance

Matrix4 = NDArray[np.float64]
Vec = NDArray[np.float64]
GATE_GROWTH_MM_S = 250.0  # the validation gate widens this fast while poses are refused
GATE_GROWTH_DEG_S = 90.0
INTEGRATE_WITHIN_MM = 5.0  # tracking's integral term runs only this close to the goal
INTEGRATE_WITHIN_DEG = 2.0
REST_FRAMES = 30  # an approach's target at rest: the goal from the mean of this many poses
# seen from within this of one viewpoint: the poses of the final creep, not of the approach
# (a mean over the last millimetre kept 0.06-0.13 mm of its errors at the TCP)
REST_VIEWPOINT_MM = 0.1
REST_VIEWPOINT_DEG = 0.02
REST_MM_S = 1.0  # at rest: the filtered speed under this
REST_DEG_S = 0.2
BOUND_SIGMAS = 2.0  # the estimated error adds this many standard errors of the goal


@dataclass(frozen=True)
class ServoGoal:
    T_target_tcp: Matrix4
    standoff_mm: float

    def tcp(self, T_base_target: Matrix4) -> Matrix4:
        return approach_tcp(T_base_target, self.T_target_tcp, self.standoff_mm)


@dataclass(frozen=True)
class Aim:
    estimate: TargetEstimate  # the target now (or held: the last pose seen)
    goal: Matrix4  # the TCP's


class PositionLaw(Law[Located, Aim]):
    """The law of one servo run (module doc); its measurements are the located frames."""

    name = "servo"
    doing = "while servoing"
    unseen = "pose did not show the target"
    blind_frames_examined = True

    def __init__(self, core: CellCore, goal: ServoGoal, mode: LoopMode) -> None:
        self.core, self.goal, self.mode = core, goal, mode
        self.sc = sc = core.config.servo
        self.max_age_s = core.config.limits.max_pose_age_s
        self.phase: str = mode
        self.event_mode: str = mode
        self.timeout_s = sc.approach_timeout_s
        self.caps = c = StreamCaps.of(core.config)
        self.params = LawParams(sc.gain_lin_per_s, sc.gain_rot_per_s, c.max_speed_mm_s,
                                c.max_rate_rad_s, c.accel_mm_s2, sc.watchdog_s, c.accel_rad_s2)
        self.filter = ConstantVelocityFilter(sc.filter_alpha, sc.filter_beta)
        self.gated = 0  # poses rejected by the validation gate
        self.ki = sc.track_integral_per_s2 if mode == "track" else 0.0
        self.i_lin, self.i_rot = np.zeros(3), np.zeros(3)
        self.consecutive = 0  # frames within the tolerance in a row
        self.last_error = (float("nan"), float("nan"))
        # a fixed camera's approach holds the last pose seen while the arm hides the target
        self.may_hold = core.frames.is_fixed and mode == "approach"
        self.held: TargetEstimate | None = None
        self.held_frames = -1
        self.occlusions = 0  # times it held the last pose seen
        self.occlusion_reason: str | None = None
        self.rest = RestMean(REST_FRAMES, REST_VIEWPOINT_MM, REST_VIEWPOINT_DEG) \
            if mode == "approach" else None
        self.rest_cache: tuple[int, TargetEstimate] | None = None  # (frames, the mean's)
        self.rest_used = False  # the last aim was the mean of the poses at rest
        # once converged the mean stays the one it converged on: the frames seen while the arm
        # stops must not change (or restart) the goal the result reports and claims by
        self.rest_frozen = False

    # -- per frame -----------------------------------------------------------------------------
    def seed(self, first: Located) -> None:
        """The job's own locate starts the filter; it is not one of the loop's frames."""
        self.filter.update(first.frame_timestamp_s, first.T_base_target)

    def read(self, located: Located) -> Located:
        return located

    def admit(self, located: Located) -> None:
        t, T_bt = located.frame_timestamp_s, located.T_base_target
        d_mm, d_deg = self.filter.innovation(t, T_bt)
        # the gate widens with the time since the last pose it let in, by what the target
        # could have moved meanwhile, so it cannot lock a moving target out
        silent_s = max(0.0, t - self.filter.predict(t).measured_at_s)
        if d_mm > self.sc.gate_mm + GATE_GROWTH_MM_S * silent_s \
                or d_deg > self.sc.gate_deg + GATE_GROWTH_DEG_S * silent_s:
            self.gated += 1  # not this target's motion: a wrong match
            raise Unusable(RefusedError(ErrorCode.pose_jump, f"a pose {d_mm:.1f} mm / "
                                        f"{d_deg:.1f} deg from the prediction was not used"),
                           failed=False)
        self.filter.update(t, T_bt)
        if self.rest is not None and not self.rest_frozen:
            self.rest.add(T_bt, located.T_base_tcp)

    # -- per tick ------------------------------------------------------------------------------
    def aim(self, now: Tick[Located]) -> Aim | None:
        est = self.filter.predict(now.t, max_horizon_s=self.sc.max_predict_s)
        if self.held is not None and now.frames != self.held_frames:
            self.held = None  # seen again: live poses drive the goal
        occluded = now.silence.lost or now.t - est.measured_at_s > self.max_age_s
        if self.held is None and occluded and self.may_hold and now.camera_running:
            last = self.filter.predict(est.measured_at_s)
            self.held = TargetEstimate(last.T_base_target, np.zeros(3), np.zeros(3),
                                       last.measured_at_s)
            self.held_frames = now.frames
            self.occlusions += 1
            if self.occlusion_reason is None and now.why_unseen is not None:
                self.occlusion_reason = now.why_unseen.message
        self.rest_used = False
        if self.held is not None:
            est = self.held
        elif now.silence.lost:
            return None
        elif now.t - est.measured_at_s > self.max_age_s:
            raise RefusedError(ErrorCode.stale_pose, f"the newest target pose is "
                               f"{now.t - est.measured_at_s:.2f} s old (limit {self.max_age_s} s)")
        else:
            est = self._at_rest(est, now.frames)
        return Aim(est, self.goal.tcp(est.T_base_target))

    def _at_rest(self, est: TargetEstimate, frames: int) -> TargetEstimate:
        """An approach's target at rest: the mean of its poses from this viewpoint
        (:mod:`cell.servoing.rest_mean`) instead of the filter's, which follows each frame."""
        rest = self.rest
        if rest is None or len(rest) < 3 \
                or float(np.linalg.norm(est.velocity_mm_s)) > REST_MM_S \
                or float(np.degrees(np.linalg.norm(est.angular_velocity_rad_s))) > REST_DEG_S:
            return est
        if self.rest_cache is None or self.rest_cache[0] != frames:
            self.rest_cache = (frames, TargetEstimate(rest.mean(), np.zeros(3), np.zeros(3),
                                                      est.measured_at_s))
        self.rest_used = True
        return self.rest_cache[1]

    def judge(self, aim: Aim, T_tcp: Matrix4, new: bool, t_s: float, prev: Vec
              ) -> Reading | None:
        if not new and self.held is None:
            return None
        if new:  # a new goal to check
            self.core.arm.guard.check_path(linear_path(T_tcp, aim.goal), "servo goal")
        # (held, between frames: no frames to judge by, the arm's own pose every tick)
        e_mm, e_deg = self.last_error = pose_distance(T_tcp, aim.goal)
        if self.mode == "approach":
            # a fixed camera's held pose is one frame's: nothing more to wait for
            averaged = self.held is not None or (
                self.rest_used and self.rest is not None
                and len(self.rest) >= self.sc.rest_frames)
            ok = e_mm < self.sc.tolerance_mm and e_deg < self.sc.tolerance_deg
            self.consecutive = self.consecutive + 1 if ok else 0
            converged = averaged and self.consecutive >= self.sc.converge_frames
            if converged and self.held is None:
                self.rest_frozen = True
            return Reading({"error_mm": e_mm, "error_deg": e_deg}, converged=converged)
        return Reading({"error_mm": e_mm, "error_deg": e_deg}, converged=False)

    def twist(self, aim: Aim, T_tcp: Matrix4, state: ArmState, t: float, clock: TwistClock
              ) -> Vec:
        est, goal = aim.estimate, aim.goal
        ff = goal_velocity(est.T_base_target, goal, est.velocity_mm_s,
                           est.angular_velocity_rad_s)
        dt = clock.step()
        if self.ki > 0:
            e_p, e_r = pose_error(T_tcp, goal)
            # integrate only near the goal: the pull-in transient would wind it up
            if np.linalg.norm(e_p) < INTEGRATE_WITHIN_MM:
                self.i_lin = integrate(self.i_lin, e_p, dt, self.ki,
                                       0.2 * self.params.max_speed_mm_s)
            if np.degrees(np.linalg.norm(e_r)) < INTEGRATE_WITHIN_DEG:
                self.i_rot = integrate(self.i_rot, e_r, dt, self.ki,
                                       0.2 * self.params.max_angular_speed_rad_s)
            ff = ff + self.ki * np.concatenate([self.i_lin, self.i_rot])
        return pbvs_twist(T_tcp, goal, ff, clock.prev, dt, self.params)

    def left(self) -> str:
        return f"error {self.last_error[0]:.2f} mm / {self.last_error[1]:.3f} deg"

    def lost_detail(self, stats: FrameStats) -> str:
        return f"{self.gated} gated as jumps, {stats.stale} too old"

    # -- at the end ----------------------------------------------------------------------------
    def result(self, loop: Loop[Located], reached: Matrix4) -> dict[str, Any]:
        with loop.lock:
            est = self.held or self.filter.predict(time.monotonic())
            mean = None
            if self.rest_used and self.rest is not None and self.held is None:
                T_bt = self.rest.mean()
                mean = self.rest.at(invert_T(T_bt) @ self.goal.tcp(T_bt))
                est = TargetEstimate(mean.T_base_target, est.velocity_mm_s,
                                     est.angular_velocity_rad_s, est.measured_at_s)
        goal = self.goal.tcp(est.T_base_target)
        reach_mm, reach_deg = pose_distance(reached, goal)
        # the claim: the TCP against the goal, and the goal's own uncertainty (one frame's
        # when it was not averaged: the error is then only as good as the last frame)
        sem_mm, sem_deg = (mean.sem_mm, mean.sem_deg) if mean is not None \
            and np.isfinite(mean.sem_mm) else (0.0, 0.0)
        seen = loop.newest()
        res = None if seen is None else located_resolution(self.core, seen,
                                                           1 if mean is None else mean.frames)
        res_mm, res_deg = (0.0, 0.0) if res is None else (res.mm, res.deg)
        out: dict[str, Any] = {
            "gated_frames": self.gated,
            "T_base_target": Pose.from_T(est.T_base_target), "goal_T_base_tcp": Pose.from_T(goal),
            "estimated_error_mm": self.last_error[0] + BOUND_SIGMAS * sem_mm + res_mm,
            "estimated_error_deg": self.last_error[1] + BOUND_SIGMAS * sem_deg + res_deg,
            "resolution_mm": None if res is None else res.mm,
            "resolution_deg": None if res is None else res.deg,
            "goal_frames_averaged": None if mean is None else mean.frames,
            "reach_error_mm": reach_mm, "reach_error_deg": reach_deg,
            "pose_interval_ms": ms_stats(loop.stats.gaps[1:]),
            "target_velocity_mm_s": est.velocity_mm_s.tolist(),
        }
        if self.core.frames.is_fixed:
            held = self.held
            out.update(camera_mount="fixed", pose_source="live" if held is None else "last_seen",
                       occluded=self.occlusions > 0, occluded_at_goal=held is not None,
                       occlusions=self.occlusions, occlusion_reason=self.occlusion_reason,
                       pose_age_s=None if held is None
                       else time.monotonic() - held.measured_at_s)
        if self.mode == "track":
            rows = loop.history.rows
            tail = [r for r in rows if r["t_s"] >= 1.0] or rows
            out["rms_error_mm"] = float(np.sqrt(np.mean([r["error_mm"] ** 2 for r in tail]))) \
                if tail else None
        return out


def located_resolution(core: CellCore, located: Located, frames: int) -> Resolution | None:
    """What a hand camera's pose estimate resolves at the TCP (:mod:`cell.servoing.
    view_bound`), the dots' centres through ``[ibvs] centroid_bias_px``; None with a fixed
    camera (its error at the tool is not the hand's lever)."""
    if core.frames.is_fixed:
        return None
    locator = core.locator
    return pose_resolution(locator.camera_model, located.result, locator.target.points_mm,
                           invert_T(core.frames.T_tcp_camera),
                           core.config.ibvs.centroid_bias_px, frames)
