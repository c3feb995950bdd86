"""Image-based visual servoing to a taught view (approach and track, mode ``"ibvs"``).

Two threads per run, as :mod:`cell.actions.servo`. The frame thread estimates every new frame and
keeps the newest view: the matched dots' normalised image points (undistorted through the lens
model), their depths and 3-D positions from the frame's pose estimate, and the arm pose at
the frame's mid-exposure time. Only the dots the taught view also has are used (the estimator's
correspondence names them), so a dot that leaves the image or is hidden just drops out; a view
with fewer than 4 of them is no view (the lost-target clock runs, then ``target_lost``).

The control loop ticks at ``[servo] tick_s``. It takes the newest measured features (with
``[ibvs] predict_motion``, moved on by the camera's motion since their exposure, from the arm's
pose history: :func:`cell.actions.ibvs.predicted`; at rest nothing is added), computes the law's
camera twist (:mod:`cell.actions.ibvs`) with the adaptive gain capped at ``[ibvs]
gain_latency_product`` over the loop's delay (the view's age when used, averaged), maps it to
the TCP's base-frame twist through the hand-eye transform, caps its speed and acceleration by
the ``[servo]`` limits, and sends it through the guarded arm's ``servo_twist`` (every tick
checked, the arm's watchdog brakes if ticks stop, a stop cancels the holder). Each new view's
pose-based goal (``T_base_target @ T_target_tcp``) is checked against the envelope like the
servo's, and reported as the estimated pose error; the law itself never uses it. An
approach's own locate is the loop's first view.

Converged (approach): over the last ``[ibvs] converge_frames`` measured frames, the image error
averaged under ``tolerance_px_rms`` (RMS over the dots) and ``tolerance_px_max`` (the worst
dot); averaged, because the view's weakest direction (a turn about a point near the target,
which moves the image only through perspective) is below one frame's noise. The TCP motion
the window's mean view still asks for (:func:`cell.actions.ibvs.remaining_motion`) under
``tolerance_mm`` / ``tolerance_deg``: the pixels alone cannot see that weakest direction, and
the mean view's step, unlike a mean of per-frame steps, is not the frames' noise. And the arm
nearly still: a window's mean is small too while the arm swings through the view.
"""

from __future__ import annotations

import logging
import threading
import time
from collections import deque
from dataclasses import dataclass
from typing import Any, Literal

import numpy as np
from numpy.typing import NDArray

from cell.actions.ibvs import (
    MIN_FEATURES,
    AdaptiveGain,
    Features,
    LatencyCappedGain,
    features_from_view,
    image_error_px,
    limit_twist,
    predicted,
    remaining_motion,
)
from cell.actions.ibvs_mount import IbvsMount
from cell.actions.ibvs_settle import mean_features, settle_step, step_size
from cell.actions.servo import (
    MAX_EXTRAPOLATE_S,
    PROGRESS_PERIOD_S,
    _stats_ms,
    stop_still,
)
from cell.actions.target_loss import LossClock, Silence
from cell.core import CellCore
from cell.error_codes import ErrorCode
from cell.errors import CellError, RefusedError, UnavailableError
from cell.motion.guard import SERVO_MIN_DT_S, Motion
from cell.motion.limits import linear_path
from cell.motion.twist import extrapolate_tcp
from cell.vision.locate import Located
from drivers.errors import DriverError
from estimator.transforms import pose_dict, pose_distance

log = logging.getLogger(__name__)
Matrix4 = NDArray[np.float64]
IbvsMode = Literal["approach", "track"]
HISTORY_POINTS = 100
LATENCY_SMOOTHING_S = 0.2  # the time constant the loop's delay is averaged over
STILL_SHARE = 0.5  # converged only if the arm moves less than this share of the tolerances
# within the loop's delay


@dataclass(frozen=True)
class View:
    """One measured frame, reduced to what the law needs."""

    features: Features  # only the dots the taught view has
    points_camera_mm: NDArray[np.float64]  # those dots in the camera frame (pose estimate)
    T_base_tcp: Matrix4  # at mid-exposure
    T_base_target: Matrix4  # the pose estimate in the base frame (for the goal check)
    exposure_s: float
    sequence: int
    border_px: float  # the smallest distance of a matched dot from the image's edge
    missing: tuple[int, ...]  # taught dots not matched in this frame


class IbvsRun:
    """One IBVS job's loop (module doc). ``run`` returns the job's result."""

    def __init__(self, core: CellCore, job_id: str, motion: Motion, desired: Features,
                 T_target_tcp: Matrix4, mode: IbvsMode, *,
                 duration_s: float | None = None) -> None:
        self.core, self.job_id, self.motion, self.mode = core, job_id, motion, mode
        self.desired, self.T_target_tcp, self.duration_s = desired, T_target_tcp, duration_s
        self.sc, self.ic, lim = core.config.servo, core.config.ibvs, core.config.limits
        self.mount = IbvsMount.of(core.frames, desired, core.locator.target.points_mm)
        self.gain = AdaptiveGain(self.ic.gain_at_zero_per_s, self.ic.gain_at_infinity_per_s,
                                 self.ic.slope_at_zero)
        self.max_speed_mm_s = min(self.sc.max_speed_mm_s, lim.max_speed_mm_s)
        self.max_rate_rad_s = float(np.radians(min(self.sc.max_angular_speed_deg_s,
                                                   lim.max_angular_speed_deg_s)))
        self.accel_mm_s2 = min(self.sc.accel_mm_s2, lim.max_accel_mm_s2)
        self.accel_rad_s2 = float(np.radians(min(self.sc.angular_accel_deg_s2,
                                                 lim.max_angular_accel_deg_s2)))
        self._lock = threading.Lock()
        self._done = threading.Event()
        self._view: View | None = None
        self._frames = 0
        self._failed_frames = 0
        self._stale_frames = 0
        self._few_dots_frames = 0
        self._frames_missing_dots = 0
        self._min_dots = len(desired.ids)
        self._min_border_px = float("inf")
        # loss judged on camera time, as the pose-based servo does (cell.actions.target_loss)
        sc = self.sc
        self._loss = LossClock(sc.lost_after_s, max(sc.stall_after_s, sc.lost_after_s),
                               time.monotonic())
        self._lags: list[float] = []
        self._camera_error: CellError | None = None
        self._last_error: CellError | None = None
        self._last_sequence = -1
        self._thread_error: Exception | None = None

    # -- the frame thread ----------------------------------------------------------------------
    def _frame_thread(self) -> None:
        try:
            self._frame_loop()
        except Exception as err:  # the control loop sees it and stops the arm
            log.exception("the IBVS frame thread failed")
            self._thread_error = err

    def _frame_loop(self) -> None:
        locator = self.core.locator
        max_age = self.core.config.limits.max_pose_age_s
        while not self._done.is_set():
            try:
                frame, result, T_base_tcp = locator.measure_view(self._last_sequence, 0.5)
            except UnavailableError as err:
                self._camera_error = err
                self._done.wait(0.02)
                continue
            except CellError as err:
                if err.code != "no_new_frame":
                    self._failed_frames += 1
                    self._last_error = err
                continue
            self._camera_error = None
            self._last_sequence = frame.sequence
            now = time.monotonic()
            if now - frame.timestamp_s > max_age:
                self._stale_frames += 1
                with self._lock:
                    self._loss.examined(frame.timestamp_s)
                continue
            # the lens model the estimator used for this frame (teaching used it too)
            try:
                view = self._view_of(locator.camera_model, result, T_base_tcp,
                                     frame.timestamp_s, frame.sequence)
            except (ValueError, IndexError, np.linalg.LinAlgError) as err:
                # a degenerate estimate (a dot behind the camera, a bad id): not a view
                log.warning("frame %d gave no IBVS view: %r", frame.sequence, err)
                self._failed_frames += 1
                self._last_error = RefusedError(ErrorCode.estimation_failed, f"no view: {err}")
                with self._lock:
                    self._loss.examined(frame.timestamp_s)
                continue
            if view is None:
                with self._lock:
                    self._loss.examined(frame.timestamp_s)
                continue
            self._keep(view, now)

    def _keep(self, view: View, now_s: float) -> None:
        """``view`` is the newest; its frame counted."""
        with self._lock:
            self._view = view
            self._last_sequence = max(self._last_sequence, view.sequence)
            self._frames += 1
            self._loss.pose(view.exposure_s)
            self._lags.append(now_s - view.exposure_s)
            self._min_dots = min(self._min_dots, len(view.features.ids))
            self._min_border_px = min(self._min_border_px, view.border_px)
            if view.missing:
                self._frames_missing_dots += 1

    def _view_of(self, camera: Any, result: Any, T_base_tcp: Matrix4, exposure_s: float,
                 sequence: int) -> View | None:
        locator = self.core.locator
        if result.image_points_px is None or not result.matched_ids:
            self._failed_frames += 1
            return None
        points = locator.target.points_mm
        seen = features_from_view(camera, result.matched_ids, result.image_points_px,
                                  result.T_camera_target, points)
        common = tuple(i for i in self.desired.ids if i in seen.ids)
        if len(common) < MIN_FEATURES:
            self._few_dots_frames += 1
            self._last_error = RefusedError(
                ErrorCode.target_lost, f"only {len(common)} of the taught view's dots matched (at "
                f"least {MIN_FEATURES} are needed)")
            return None
        px = np.asarray(result.image_points_px, dtype=float).reshape(-1, 2)
        border = float(np.min(np.concatenate([px[:, 0], px[:, 1],
                                              camera.width - 1 - px[:, 0],
                                              camera.height - 1 - px[:, 1]])))
        P = np.asarray(points, dtype=float)[list(common)]
        Tc = result.T_camera_target
        return View(seen.subset(common), P @ Tc[:3, :3].T + Tc[:3, 3], T_base_tcp,
                    self.core.frames.T_base_target(T_base_tcp, Tc), exposure_s, sequence,
                    border, tuple(i for i in self.desired.ids if i not in common))

    # -- the control loop ----------------------------------------------------------------------
    def run(self, first: Located | None = None) -> dict[str, Any]:
        """The loop; ``first``: the approach's own locate, whose frame serves as the loop's
        first view (the next frame would otherwise be waited for and estimated again)."""
        thread = threading.Thread(target=self._frame_thread, daemon=True,
                                  name=f"ibvs-frames-{self.job_id}")
        with self._lock:
            self._loss.restart(time.monotonic())
        if first is not None:
            self._seed(first)
        thread.start()
        try:
            out = self._control()
        finally:
            self._done.set()
            joined_s = time.monotonic()
            thread.join(timeout=2.0)
        if "phases_s" in out:
            out["phases_s"]["frame_thread_join"] = round(time.monotonic() - joined_s, 4)
        return out

    def _seed(self, first: Located) -> None:
        if time.monotonic() - first.frame_timestamp_s > self.core.config.limits.max_pose_age_s:
            return
        try:
            view = self._view_of(self.core.locator.camera_model, first.result, first.T_base_tcp,
                                 first.frame_timestamp_s, first.frame_sequence)
        except (ValueError, IndexError, np.linalg.LinAlgError):
            return
        if view is not None:
            self._keep(view, first.located_at_s)

    def _control(self) -> dict[str, Any]:
        core, sc, ic, arm, mount = self.core, self.sc, self.ic, self.core.arm, self.mount
        cam = core.locator.camera_model
        t0 = time.monotonic()
        prev = np.zeros(6)
        t_prev: float | None = None
        seen = -1
        window: deque[NDArray[np.float64]] = deque(maxlen=ic.converge_frames)
        last_step = (float("nan"), float("nan"))
        converged_s: float | None = None
        history: list[tuple[float, float, float, float]] = []
        last_px = (float("nan"), float("nan"))
        last_pose = (float("nan"), float("nan"))
        shown_s = 0.0
        phases: dict[str, float] = {}  # when each phase began (s from the loop's start)
        delay_s: float | None = None  # the loop's delay, averaged: the view's age + a tick
        caps: list[float] = []
        t_tick: float | None = None
        while True:
            tick = time.monotonic()
            self.motion.raise_if_cancelled("while servoing on the image")
            if self._thread_error is not None:
                self._stop_still()
                raise RefusedError(ErrorCode.estimator_failed, f"the IBVS frame thread failed: "
                                   f"{self._thread_error!r}")
            with self._lock:
                silence, view = self._loss.silence(tick), self._view
            if silence.lost or view is None:
                if silence.lost:
                    self._lost(silence)
                time.sleep(sc.tick_s)
                continue
            try:
                state = arm.state()
            except DriverError as err:
                raise UnavailableError(ErrorCode.arm_disconnected,
                                       f"reading the arm: {err}") from err
            held_s = 0.0 if t_prev is None else min(tick, t_prev + sc.watchdog_s) \
                - state.timestamp_s
            T_tcp = extrapolate_tcp(state.T_base_tcp, prev,
                                    min(max(held_s, 0.0), MAX_EXTRAPOLATE_S))
            desired = self.desired.subset(view.features.ids)
            if view.sequence != seen:  # a new view: its goal checked, its error judged
                seen = view.sequence
                phases.setdefault("first_view", tick - t0)
                goal = mount.goal(view.T_base_target, view.T_base_tcp, self.T_target_tcp)
                arm.guard.check_path(linear_path(T_tcp, goal), "ibvs goal estimate")
                last_pose = pose_distance(view.T_base_tcp, goal)
                last_px = image_error_px(view.features, desired, cam)
                history.append((tick - t0, last_px[0], last_pose[0], last_pose[1]))
                core.events.publish("servo", {"job_id": self.job_id, "mode": "ibvs",
                                              "t_s": tick - t0, "image_error_px": last_px[0],
                                              "error_mm": last_pose[0],
                                              "error_deg": last_pose[1]})
                if tick - shown_s >= PROGRESS_PERIOD_S:
                    shown_s = tick
                    core.runner.progress(self.job_id, {
                        "phase": f"ibvs_{self.mode}", "t_s": round(tick - t0, 3),
                        "image_error_px": last_px[0], "error_mm": last_pose[0],
                        "error_deg": last_pose[1], "dots": len(view.features.ids)})
                if self.mode == "approach":
                    window.append(view.features.xy - desired.xy)
                    step = remaining_motion(view.features, desired, ic.interaction,
                                            mount.camera_tcp(view.T_base_tcp))
                    if step[0] < ic.tolerance_mm and step[1] < ic.tolerance_deg:
                        phases.setdefault("first_frame_within", tick - t0)
                    if len({e.shape for e in window}) > 1:  # the dots changed: start again
                        window.clear()
                        window.append(view.features.xy - desired.xy)
                    if len(window) >= ic.converge_frames:
                        last_px = _window_px(window, cam)
                        # the motion the window's mean view asks for: a mean of per-frame
                        # steps would be each frame's noise, not the view's offset
                        mean_view = Features(desired.ids, desired.xy + np.mean(window, axis=0),
                                             view.features.depth_mm)
                        last_step = remaining_motion(mean_view, desired, ic.interaction,
                                                     mount.camera_tcp(view.T_base_tcp))
                        # and the arm nearly still: a window's mean is also small while the
                        # arm swings through the view; within the loop's delay (what the
                        # newest view is behind the arm) it may move half the tolerance
                        lag_s = 0.0 if delay_s is None else delay_s
                        if last_px[0] < ic.tolerance_px_rms and last_px[1] < ic.tolerance_px_max:
                            phases.setdefault("window_image_within", tick - t0)
                        if last_step[0] < ic.tolerance_mm and last_step[1] < ic.tolerance_deg:
                            phases.setdefault("window_view_within", tick - t0)
                        still = float(np.linalg.norm(prev[:3])) * lag_s \
                            < STILL_SHARE * ic.tolerance_mm \
                            and float(np.degrees(np.linalg.norm(prev[3:]))) * lag_s \
                            < STILL_SHARE * ic.tolerance_deg
                        if still:
                            phases.setdefault("window_still", tick - t0)
                        if last_px[0] < ic.tolerance_px_rms \
                                and last_px[1] < ic.tolerance_px_max \
                                and last_step[0] < ic.tolerance_mm \
                                and last_step[1] < ic.tolerance_deg and still:
                            converged_s = tick - t0
                            break
            if self.mode == "approach" and tick - t0 > ic.approach_timeout_s:
                self._stop_still()
                raise RefusedError(ErrorCode.servo_timeout, f"the IBVS approach did not converge "
                                   f"within {ic.approach_timeout_s} s (image error "
                                   f"{last_px[0]:.3f} px RMS, {last_px[1]:.3f} px max)")
            if self.mode == "track" and self.duration_s is not None \
                    and tick - t0 >= self.duration_s:
                break
            now_features = predicted(view.features, mount.dots_motion(T_tcp, view.T_base_tcp),
                                     view.points_camera_mm) if ic.predict_motion \
                else view.features
            # what the command acts on is as old as the view, or with the view moved on by
            # the arm's motion since its exposure, as old as the arm's state
            age_s = max(tick - (state.timestamp_s if ic.predict_motion else view.exposure_s),
                        0.0) + sc.tick_s
            delay_s = age_s if delay_s is None or t_tick is None else delay_s + (
                age_s - delay_s) * min(1.0, (tick - t_tick) / LATENCY_SMOOTHING_S)
            t_tick = tick
            gain = LatencyCappedGain(self.gain, delay_s, ic.gain_latency_product)
            caps.append(gain.cap_per_s)
            twist = mount.tcp_twist(now_features, desired, gain, ic.interaction, T_tcp)
            t_cmd = time.monotonic()
            accepted_s = arm.last_twist_s
            dt = SERVO_MIN_DT_S if t_prev is None or accepted_s is None else min(
                max(t_cmd - accepted_s, SERVO_MIN_DT_S), 2.0 * sc.tick_s)
            if t_prev is not None and t_cmd - t_prev > 0.75 * sc.watchdog_s:
                prev = np.zeros(6)
            twist = limit_twist(twist, prev, dt, self.max_speed_mm_s, self.max_rate_rad_s,
                                self.accel_mm_s2, self.accel_rad_s2)
            arm.servo_twist(twist, self.accel_mm_s2, sc.watchdog_s, self.accel_rad_s2)
            prev, t_prev = twist, t_cmd
            rest = tick + sc.tick_s - time.monotonic()
            if rest > 0:
                time.sleep(rest)
        if converged_s is not None:
            phases["converged"] = converged_s
        self._stop_still()
        phases["stopped"] = time.monotonic() - t0
        settle: dict[str, Any] = {}
        if self.mode == "approach" and ic.settle_frames > 0:
            settle = self._settle()
            converged_s = time.monotonic() - t0
            phases["settled"] = converged_s
        return self._result(t0, converged_s, last_px, last_pose, history) | {
            "view_error_mm": last_step[0], "view_error_deg": last_step[1],
            "phases_s": {k: round(v, 4) for k, v in phases.items()},
            "gain_cap_per_s": _percentiles(caps)} | settle

    # -- the final settle (cell.actions.ibvs_settle) ---------------------------------------------
    def _settle(self) -> dict[str, Any]:
        """Average ``settle_frames`` views with the arm still, step by ``-L^+ e``; up to
        ``settle_steps`` times, until the step is under the settle tolerance."""
        ic, arm = self.ic, self.core.arm
        sizes: list[list[float]] = []
        for _ in range(ic.settle_steps):
            views = self._rest_views(ic.settle_frames, time.monotonic())
            step = settle_step(mean_features([v.features for v in views]), self.desired)
            size = step_size(step, self.mount.camera_tcp(views[-1].T_base_tcp))
            sizes.append([round(size[0], 4), round(size[1], 5)])
            if size[0] < ic.settle_tolerance_mm and size[1] < ic.settle_tolerance_deg:
                break
            self.motion.raise_if_cancelled("before the IBVS settle step")
            goal = self.mount.step_goal(views[-1].T_base_tcp, step)
            try:
                arm.move_linear(goal, self.max_speed_mm_s, self.accel_mm_s2,
                                what="IBVS settle step")
            finally:
                self._stop_still()
        return {"settle_steps_mm_deg": sizes}

    def _rest_views(self, n: int, after_s: float) -> list[View]:
        """``n`` new views exposed after ``after_s`` (the arm is still by then)."""
        views: list[View] = []
        deadline = time.monotonic() + 2.0 + 6.0 * n / self.core.config.camera.fps
        while len(views) < n:
            self.motion.raise_if_cancelled("while settling on the image")
            with self._lock:
                view = self._view
            if view is not None and view.exposure_s > after_s and \
                    (not views or view.sequence != views[-1].sequence):
                views.append(view)
            elif time.monotonic() > deadline:
                raise RefusedError(ErrorCode.target_lost, f"only {len(views)} of {n} views of "
                                   "the still arm arrived for the IBVS settle")
            else:
                time.sleep(0.002)
        return views

    def _result(self, t0: float, converged_s: float | None, last_px: tuple[float, float],
                last_pose: tuple[float, float],
                history: list[tuple[float, float, float, float]]) -> dict[str, Any]:
        reached = self.core.arm.state().T_base_tcp
        with self._lock:
            view = self._view
        out: dict[str, Any] = {
            "mode": "ibvs" if self.mode == "approach" else "ibvs_track",
            "frames": self._frames, "failed_frames": self._failed_frames,
            "stale_frames": self._stale_frames,
            "frames_with_too_few_dots": self._few_dots_frames,
            "frames_missing_dots": self._frames_missing_dots,
            "min_dots_used": self._min_dots,
            "dots_taught": len(self.desired.ids),
            "min_dot_border_px": None if not np.isfinite(self._min_border_px)
            else self._min_border_px,
            "interaction": self.ic.interaction,
            "image_error_px_rms": last_px[0], "image_error_px_max": last_px[1],
            "estimated_error_mm": last_pose[0], "estimated_error_deg": last_pose[1],
            "reached_T_base_tcp": pose_dict(reached),
            "pose_latency_ms": _stats_ms(self._lags),
            "error_history": _downsample(history),
        }
        if view is not None:
            out["T_base_target"] = pose_dict(view.T_base_target)
            out["goal_T_base_tcp"] = pose_dict(view.T_base_target @ self.T_target_tcp)
        if self.mode == "approach":
            out.update(converged=True, time_to_converge_s=converged_s)
        else:
            out.update(duration_s=time.monotonic() - t0)
        return out

    def _stop_still(self) -> float:
        return stop_still(self.core.arm, self.sc.stop_decel_mm_s2)

    def _lost(self, silence: Silence) -> None:
        declared_s = time.monotonic()
        took = self._stop_still()
        why = self._camera_error or self._last_error
        self.core.runner.progress(self.job_id, {"phase": "target_lost",
                                                "stopped_in_ms": round(took * 1000.0, 1),
                                                "lost_at_monotonic_s": declared_s})
        what = silence.describe(self.sc.lost_after_s, self._loss.stall_after_s,
                                "view were not usable")
        raise RefusedError(ErrorCode.target_lost, what
                           + (f"; {why.message}" if why is not None else "")
                           + f"; {self._failed_frames} frames without the target, "
                           f"{self._few_dots_frames} with fewer than {MIN_FEATURES} taught "
                           f"dots; the arm stopped in {took * 1000:.0f} ms")


def _window_px(window: deque[NDArray[np.float64]], camera: Any) -> tuple[float, float]:
    """RMS and max over the dots of the image error averaged over the window's frames (px):
    where the view rests, its frame-to-frame noise averaged out."""
    d = np.mean(np.stack(list(window)), axis=0) * np.array([camera.fx, camera.fy])
    n = np.linalg.norm(d, axis=1)
    return float(np.sqrt(np.mean(n ** 2))), float(np.max(n))


def _percentiles(xs: list[float]) -> dict[str, float] | None:
    if not xs:
        return None
    p5, p50, p95 = np.percentile(xs, [5, 50, 95])
    return {"p5": round(float(p5), 2), "median": round(float(p50), 2), "p95": round(float(p95), 2)}


def _downsample(rows: list[tuple[float, float, float, float]], n: int = HISTORY_POINTS
                ) -> list[dict[str, float]]:
    if len(rows) > n:
        idx = np.unique(np.linspace(0, len(rows) - 1, n).round().astype(int))
        rows = [rows[i] for i in idx]
    return [{"t_s": round(t, 4), "image_error_px": round(px, 4), "error_mm": round(e, 4),
             "error_deg": round(d, 4)} for t, px, e, d in rows]
