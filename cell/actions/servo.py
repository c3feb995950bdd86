"""Closed-loop visual servoing: approach on the fly and follow a moving target (PBVS).

Two threads per run. The frame thread estimates every new frame (the estimator tracks from
frame to frame), pairs it with the arm pose at the frame's mid-exposure time from the arm's
pose history (latency compensation: the pose the frame was taken from, not the pose now) and
folds the base-frame target pose into a constant-velocity filter. The control loop, in the
job's thread, runs at ``[servo] tick_s``: it predicts the target pose *now*, makes the TCP goal
``T_base_target @ T_target_tcp @ translate(0, 0, -standoff)``, and sends the law's twist
(:mod:`cell.actions.servo_law`) through the guarded arm, which checks every tick. So the loop is as
fast as the arm's state, not the camera, and a frame's age costs no lag.

Safety: no measurement older than ``limits.max_pose_age_s`` is used; frames exposed
``[servo] lost_after_s`` after the last pose that did not show the target stop the arm (still
before the job fails ``target_lost``; judged on camera time, :mod:`cell.actions.target_loss`);
every new goal is checked against the envelope and tilt limit (its limit's code ends the job); a
stop cancels the slot's holder, which the next tick sees, and the arm's own watchdog brakes if
ticks stop coming.

A fixed camera (eye-to-hand): the target pose is ``T_base_camera @ T_camera_target`` with no
flange in the chain (:class:`cell.vision.frames.CellFrames`), and the law already works in the
base frame, so the loop is the same. Near the goal the arm itself hides the target from the
camera; an approach then goes on to the goal of the last pose seen, held still (as the fixed
look-and-move does), and its result says so (``pose_source = "last_seen"``, ``occluded``,
``pose_age_s``). The target must not move meanwhile: tracking with a fixed camera still ends
``target_lost``, and a stalled camera (no frames examined) always does.
"""

from __future__ import annotations

import threading
import time
from dataclasses import dataclass
from typing import Any, Literal

import numpy as np
from numpy.typing import NDArray

from cell.actions.servo_law import (
    LawParams,
    goal_velocity,
    integrate,
    pbvs_twist,
    pose_error,
)
from cell.actions.target_filter import ConstantVelocityFilter, TargetEstimate
from cell.actions.target_loss import LossClock, Silence
from cell.core import CellCore
from cell.error_codes import ErrorCode
from cell.errors import CellError, RefusedError, UnavailableError
from cell.motion.guard import SERVO_MIN_DT_S, GuardedArm, Motion
from cell.motion.limits import linear_path
from cell.motion.twist import extrapolate_tcp
from cell.vision.frames import approach_tcp
from cell.vision.locate import Located
from drivers.errors import DriverError
from estimator.transforms import pose_dict, pose_distance

Matrix4 = NDArray[np.float64]
ServoMode = Literal["approach", "track"]
HISTORY_POINTS = 100  # the error history in a job's result is downsampled to this
STILL_TIMEOUT_S = 2.0
PROGRESS_PERIOD_S = 0.25  # the job's progress carries the live error this often
PLOT_POINTS = 60
GATE_GROWTH_MM_S = 250.0  # the validation gate widens this fast while poses are refused
GATE_GROWTH_DEG_S = 90.0
INTEGRATE_WITHIN_MM = 5.0  # tracking's integral term runs only this close to the goal
INTEGRATE_WITHIN_DEG = 2.0
MAX_EXTRAPOLATE_S = 0.05  # an arm state older than this is moved on by this much only


@dataclass(frozen=True)
class ServoGoal:
    T_target_tcp: Matrix4
    standoff_mm: float

    def tcp(self, T_base_target: Matrix4) -> Matrix4:
        return approach_tcp(T_base_target, self.T_target_tcp, self.standoff_mm)


def downsample(rows: list[tuple[float, float, float]], n: int = HISTORY_POINTS
               ) -> list[dict[str, float]]:
    if len(rows) > n:
        idx = np.unique(np.linspace(0, len(rows) - 1, n).round().astype(int))
        rows = [rows[i] for i in idx]
    return [{"t_s": round(t, 4), "error_mm": round(e, 4), "error_deg": round(d, 4)}
            for t, e, d in rows]


def _stats_ms(xs: list[float]) -> dict[str, float] | None:
    if not xs:
        return None
    a = np.asarray(xs) * 1000.0
    return {"median": round(float(np.median(a)), 1), "p95": round(float(np.percentile(a, 95)), 1),
            "max": round(float(a.max()), 1)}



def stop_still(arm: GuardedArm, decel_mm_s2: float) -> float:
    """Command the stop and wait until the arm stands (at most STILL_TIMEOUT_S); the seconds
    it took. Every closed loop ends this way before it reports a lost target or a fault."""
    t0 = time.monotonic()
    try:
        arm.stop(decel_mm_s2=decel_mm_s2)
    except DriverError as err:
        raise UnavailableError(ErrorCode.arm_disconnected, f"stopping the arm: {err}") from err
    deadline = t0 + STILL_TIMEOUT_S
    while time.monotonic() < deadline:
        try:
            if not arm.state().moving:
                break
        except DriverError:
            break
        time.sleep(0.002)
    return time.monotonic() - t0

class ServoRun:
    """One servo job's loop (see module doc). ``run`` returns the job's result."""

    def __init__(self, core: CellCore, job_id: str, motion: Motion, goal: ServoGoal,
                 mode: ServoMode, *, duration_s: float | None = None,
                 first: Located | None = None) -> None:
        self.core, self.job_id, self.motion, self.goal, self.mode = core, job_id, motion, goal, mode
        sc = core.config.servo
        self.sc = sc
        self.duration_s = duration_s
        self.filter = ConstantVelocityFilter(sc.filter_alpha, sc.filter_beta)
        self._lock = threading.Lock()
        self._done = threading.Event()
        self._frames = 0
        self._failed_frames = 0
        self._stale_frames = 0
        self._last_pose_s = time.monotonic()  # host time the last pose went into the filter
        self._loss = LossClock(sc.lost_after_s, max(sc.stall_after_s, sc.lost_after_s),
                               time.monotonic(),
                               None if first is None else first.frame_timestamp_s)
        self._camera_error: CellError | None = None
        self._last_error: CellError | None = None  # why the last frame gave no pose
        self._last_sequence = -1
        self._gated = 0  # poses rejected by the validation gate
        self._occlusions = 0  # a fixed camera's approach: times it held the last pose seen
        self._occlusion_reason: str | None = None
        self._gaps: list[float] = []  # between poses arriving (s)
        self._lags: list[float] = []  # mid-exposure to pose in the filter (s)
        if first is not None:
            self.filter.update(first.frame_timestamp_s, first.T_base_target)
            self._last_pose_s = first.located_at_s
            self._last_sequence = first.frame_sequence
        self.params = LawParams(sc.gain_lin_per_s, sc.gain_rot_per_s,
                                min(sc.max_speed_mm_s, core.config.limits.max_speed_mm_s),
                                float(np.radians(min(
                                    sc.max_angular_speed_deg_s,
                                    core.config.limits.max_angular_speed_deg_s))),
                                min(sc.accel_mm_s2, core.config.limits.max_accel_mm_s2),
                                sc.watchdog_s, float(np.radians(min(
                                    sc.angular_accel_deg_s2,
                                    core.config.limits.max_angular_accel_deg_s2))))

    # -- the frame thread ----------------------------------------------------------------------
    def _frame_loop(self) -> None:
        max_age = self.core.config.limits.max_pose_age_s
        while not self._done.is_set():
            try:
                frame, T_bt, _ = self.core.locator.measure(self._last_sequence, timeout_s=0.5)
            except UnavailableError as err:
                self._camera_error = err
                self._done.wait(0.02)
                continue
            except CellError as err:
                if err.code != "no_new_frame":
                    self._failed_frames += 1
                    self._last_error = err
                    shown = self.core.locator.last_frame  # the frame it was judged on
                    if shown is not None:
                        with self._lock:
                            self._loss.examined(shown.timestamp_s)
                continue
            self._camera_error = None
            self._last_sequence = frame.sequence
            if time.monotonic() - frame.timestamp_s > max_age:
                self._stale_frames += 1  # never used: the pose it gives is too old
                with self._lock:
                    self._loss.examined(frame.timestamp_s)
                continue
            now = time.monotonic()
            with self._lock:
                d_mm, d_deg = self.filter.innovation(frame.timestamp_s, T_bt)
                # the gate widens with the time since the last pose it let in, by what the
                # target could have moved meanwhile, so it cannot lock a moving target out
                silent_s = max(0.0, frame.timestamp_s - self.filter.predict(
                    frame.timestamp_s).measured_at_s)
                gate_mm = self.sc.gate_mm + GATE_GROWTH_MM_S * silent_s
                gate_deg = self.sc.gate_deg + GATE_GROWTH_DEG_S * silent_s
                if d_mm > gate_mm or d_deg > gate_deg:
                    self._gated += 1  # not this target's motion: a wrong match
                    self._loss.examined(frame.timestamp_s)
                    self._last_error = RefusedError(
                        ErrorCode.pose_jump, f"a pose {d_mm:.1f} mm / {d_deg:.1f} deg from the "
                        "prediction was not used")
                    continue
                self.filter.update(frame.timestamp_s, T_bt)
                self._gaps.append(now - self._last_pose_s)
                self._lags.append(now - frame.timestamp_s)
                self._last_pose_s = now
                self._loss.pose(frame.timestamp_s)
                self._frames += 1

    # -- the control loop ----------------------------------------------------------------------
    def run(self) -> dict[str, Any]:
        thread = threading.Thread(target=self._frame_loop, daemon=True,
                                  name=f"servo-frames-{self.job_id}")
        with self._lock:  # the lost-target clock starts with the loop (the arm is still)
            self._last_pose_s = max(self._last_pose_s, time.monotonic())
            self._loss.restart(time.monotonic())
        thread.start()
        try:
            return self._control()
        finally:
            self._done.set()
            thread.join(timeout=2.0)

    def _control(self) -> dict[str, Any]:
        core, sc, arm = self.core, self.sc, self.core.arm
        max_age = core.config.limits.max_pose_age_s
        t0 = time.monotonic()
        prev = np.zeros(6)
        t_prev: float | None = None
        seen = -1
        consecutive = 0
        converged_s: float | None = None
        history: list[tuple[float, float, float]] = []
        last_est = (float("nan"), float("nan"))
        shown_s = 0.0
        ki = sc.track_integral_per_s2 if self.mode == "track" else 0.0
        i_lin, i_rot = np.zeros(3), np.zeros(3)
        # a fixed camera's approach holds the last pose seen while the arm hides the target
        may_hold = core.frames.is_fixed and self.mode == "approach"
        held: TargetEstimate | None = None
        held_frames = -1
        while True:
            tick = time.monotonic()
            self.motion.raise_if_cancelled("while servoing")
            with self._lock:
                silence, frames = self._loss.silence(tick), self._frames
                est = self.filter.predict(tick, max_horizon_s=sc.max_predict_s)
            if held is not None and frames != held_frames:
                held = None  # seen again: live poses drive the goal
            occluded = silence.lost or tick - est.measured_at_s > max_age
            if held is None and occluded and may_hold and self._camera_error is None \
                    and silence.stalled_s < self._loss.stall_after_s:
                with self._lock:
                    last = self.filter.predict(est.measured_at_s)
                held, held_frames = TargetEstimate(last.T_base_target, np.zeros(3), np.zeros(3),
                                                   last.measured_at_s), frames
                self._occlusions += 1
                if self._occlusion_reason is None and self._last_error is not None:
                    self._occlusion_reason = self._last_error.message
            if held is not None:
                est = held
            elif silence.lost:
                self._lost(silence)
            if held is None and tick - est.measured_at_s > max_age:
                self._stop_still()
                raise RefusedError(ErrorCode.stale_pose, f"the newest target pose is "
                                   f"{tick - est.measured_at_s:.2f} s old (limit {max_age} s)")
            goal = self.goal.tcp(est.T_base_target)
            try:
                state = arm.state()
            except DriverError as err:
                raise UnavailableError(ErrorCode.arm_disconnected,
                                       f"reading the arm: {err}") from err
            # the TCP now: the reading (a few ms old) moved on by the twist last sent, for as
            # long as the arm kept that twist (its watchdog brakes it after watchdog_s)
            held_s = 0.0 if t_prev is None else min(tick, t_prev + sc.watchdog_s) \
                - state.timestamp_s
            T_tcp = extrapolate_tcp(state.T_base_tcp, prev, min(max(held_s, 0.0),
                                                                MAX_EXTRAPOLATE_S))
            if frames != seen:  # a new measurement: a new goal to check, and a verdict
                seen = frames
                arm.guard.check_path(linear_path(T_tcp, goal), "servo goal")
                e_mm, e_deg = pose_distance(T_tcp, goal)
                last_est = (e_mm, e_deg)
                history.append((tick - t0, e_mm, e_deg))
                core.events.publish("servo", {"job_id": self.job_id, "mode": self.mode,
                                              "t_s": tick - t0, "error_mm": e_mm,
                                              "error_deg": e_deg})
                if tick - shown_s >= PROGRESS_PERIOD_S:  # the page plots the live error
                    shown_s = tick
                    core.runner.progress(self.job_id, {
                        "phase": self.mode, "t_s": round(tick - t0, 3), "error_mm": e_mm,
                        "error_deg": e_deg, "recent": downsample(history[-PLOT_POINTS:],
                                                                 PLOT_POINTS)})
                if self.mode == "approach":
                    ok = e_mm < sc.tolerance_mm and e_deg < sc.tolerance_deg
                    consecutive = consecutive + 1 if ok else 0
                    if consecutive >= sc.converge_frames:
                        converged_s = tick - t0
                        break
            elif held is not None:  # no frames to judge by: the arm's own pose, every tick
                e_mm, e_deg = pose_distance(T_tcp, goal)
                last_est = (e_mm, e_deg)
                ok = e_mm < sc.tolerance_mm and e_deg < sc.tolerance_deg
                consecutive = consecutive + 1 if ok else 0
                if consecutive >= sc.converge_frames:
                    converged_s = tick - t0
                    break
            if self.mode == "approach" and tick - t0 > sc.approach_timeout_s:
                self._stop_still()
                raise RefusedError(ErrorCode.servo_timeout, f"the servo approach did not converge "
                                   f"within {sc.approach_timeout_s} s (error {last_est[0]:.2f} "
                                   f"mm / {last_est[1]:.3f} deg)")
            if self.mode == "track" and self.duration_s is not None \
                    and tick - t0 >= self.duration_s:
                break
            ff = goal_velocity(est.T_base_target, goal, est.velocity_mm_s,
                               est.angular_velocity_rad_s)
            # the step the law may take: the acceleration over the time since the guard
            # accepted the last tick, which the guard (judging by its own clock, ticks at
            # least SERVO_MIN_DT_S apart) sees as at least as long; capped at two ticks.
            # (One nominal tick per tick lost a sixth of the acceleration: ticks come every
            # ~9.5 ms, not 8.)
            t_cmd = time.monotonic()
            accepted_s = arm.last_twist_s
            dt = SERVO_MIN_DT_S if t_prev is None or accepted_s is None else min(
                max(t_cmd - accepted_s, SERVO_MIN_DT_S), 2.0 * sc.tick_s)
            if t_prev is not None and t_cmd - t_prev > 0.75 * sc.watchdog_s:
                prev = np.zeros(6)  # a late tick: the arm's watchdog may have braked it
            if ki > 0:
                e_p, e_r = pose_error(T_tcp, goal)
                # integrate only near the goal: the pull-in transient would wind it up
                if np.linalg.norm(e_p) < INTEGRATE_WITHIN_MM:
                    i_lin = integrate(i_lin, e_p, dt, ki, 0.2 * self.params.max_speed_mm_s)
                if np.degrees(np.linalg.norm(e_r)) < INTEGRATE_WITHIN_DEG:
                    i_rot = integrate(i_rot, e_r, dt, ki,
                                      0.2 * self.params.max_angular_speed_rad_s)
                ff = ff + ki * np.concatenate([i_lin, i_rot])
            twist = pbvs_twist(T_tcp, goal, ff, prev, dt, self.params)
            arm.servo_twist(twist, self.params.accel_mm_s2, sc.watchdog_s,
                            self.params.accel_rad_s2)
            prev, t_prev = twist, t_cmd
            rest = tick + sc.tick_s - time.monotonic()
            if rest > 0:
                time.sleep(rest)
        self._stop_still()
        reached = arm.state().T_base_tcp
        with self._lock:
            est = held or self.filter.predict(time.monotonic())
        goal = self.goal.tcp(est.T_base_target)
        reach_mm, reach_deg = pose_distance(reached, goal)
        out: dict[str, Any] = {
            "mode": "servo" if self.mode == "approach" else "track",
            "frames": self._frames, "failed_frames": self._failed_frames,
            "stale_frames": self._stale_frames, "gated_frames": self._gated,
            "T_base_target": pose_dict(est.T_base_target),
            "goal_T_base_tcp": pose_dict(goal),
            "reached_T_base_tcp": pose_dict(reached),
            "estimated_error_mm": last_est[0], "estimated_error_deg": last_est[1],
            "reach_error_mm": reach_mm, "reach_error_deg": reach_deg,
            "error_history": downsample(history),
            "pose_interval_ms": _stats_ms(self._gaps[1:]),
            "pose_latency_ms": _stats_ms(self._lags),
        }
        if core.frames.is_fixed:
            out.update(camera_mount="fixed", pose_source="live" if held is None else "last_seen",
                       occluded=self._occlusions > 0, occluded_at_goal=held is not None,
                       occlusions=self._occlusions, occlusion_reason=self._occlusion_reason,
                       pose_age_s=None if held is None
                       else time.monotonic() - held.measured_at_s)
        if self.mode == "approach":
            out.update(converged=True, time_to_converge_s=converged_s,
                       target_velocity_mm_s=est.velocity_mm_s.tolist())
        else:
            tail = [r for r in history if r[0] >= 1.0] or history
            out.update(duration_s=time.monotonic() - t0,
                       rms_error_mm=float(np.sqrt(np.mean([r[1] ** 2 for r in tail])))
                       if tail else None,
                       target_velocity_mm_s=est.velocity_mm_s.tolist())
        return out

    def _stop_still(self) -> float:
        return stop_still(self.core.arm, self.sc.stop_decel_mm_s2)

    def _lost(self, silence: Silence) -> None:
        declared_s = time.monotonic()
        took = self._stop_still()
        why = self._camera_error or self._last_error
        self.core.runner.progress(self.job_id, {"phase": "target_lost",
                                                "stopped_in_ms": round(took * 1000.0, 1),
                                                "lost_at_monotonic_s": declared_s,
                                                "last_pose_exposure_s":
                                                    self._loss.last_pose_exposure_s})
        what = silence.describe(self.sc.lost_after_s, self._loss.stall_after_s)
        raise RefusedError(ErrorCode.target_lost, what
                           + (f"; {why.message}" if why is not None else "")
                           + f"; {self._failed_frames} frames without the target, "
                           f"{self._gated} gated as jumps, {self._stale_frames} too old"
                           + f"); the arm stopped in {took * 1000:.0f} ms")
