"""The closed loop every streamed motion runs: servo and IBVS, approaching and tracking.

Two threads per run. The frame thread has the locator estimate every new frame and map it into
the base frame with the arm pose at its mid-exposure time (latency compensation: the pose the
frame was taken from, not the pose now; :meth:`cell.vision.locate.Locator.measure`) and gives
it to the law (:mod:`~cell.servoing.law`). The control loop, in the job's thread, ticks at
``[servo] tick_s``: it asks the law where to go, reads the arm, moves the TCP on by the twist
last sent (:class:`~cell.servoing.clock.TwistClock`), has the law judge each new
measurement and sends the law's twist through the guarded arm, which checks every tick. So
the loop is as fast as the arm's state, not the camera, and a frame's age costs no lag.

Safety: no measurement older than ``limits.max_pose_age_s`` is used; frames exposed ``[servo]
lost_after_s`` after the last measurement that gave none stop the arm (still before the job
fails ``target_lost``; judged on camera time, :mod:`cell.servoing.target_loss`); a track that
falls behind its target stops too (``tracking_lag``, :mod:`cell.servoing.lag`); a stop cancels
the slot's holder, which the next tick sees, and the arm's own watchdog brakes if ticks stop
coming. The loop stops the arm one way (:meth:`~cell.motion.guard.GuardedArm.settle`, at
``[servo] stop_decel_mm_s2``) before it reports a lost target, a timeout or its result.
"""

from __future__ import annotations

import logging
import threading
import time
from typing import Any, Generic

from cell.core import CellCore
from cell.error_codes import ErrorCode
from cell.errors import CellError, RefusedError, UnavailableError
from cell.motion.guard import Motion
from cell.results import Pose
from cell.servoing.clock import TwistClock
from cell.servoing.lag import Lag, LagWatch
from cell.servoing.law import A, Law, M, Reading, Tick, Unusable
from cell.servoing.record import FrameStats, History, ms_stats
from cell.servoing.target_loss import LossClock, Silence
from cell.vision.locate import Located
from drivers.errors import DriverError

log = logging.getLogger(__name__)
STILL_TIMEOUT_S = 2.0  # a stop waits this long at most for the arm to stand
STILL_POLL_S = 0.002
PROGRESS_PERIOD_S = 0.25  # the job's progress carries the live error this often
PLOT_POINTS = 60


class ClosedLoop(Generic[M, A]):
    """One streamed motion's run (module doc)."""

    def __init__(self, core: CellCore, job_id: str, motion: Motion, law: Law[M, A], *,
                 duration_s: float | None = None) -> None:
        self.core, self.job_id, self.motion, self.law = core, job_id, motion, law
        self.sc = sc = core.config.servo
        self.duration_s = duration_s  # a track's; an approach runs until it converges
        self.lock = threading.Lock()
        self.stats = FrameStats()
        self.history = History()
        self.t0 = time.monotonic()
        self._done = threading.Event()
        self._loss = LossClock(sc.lost_after_s, max(sc.stall_after_s, sc.lost_after_s), self.t0)
        self._newest: M | None = None
        self._sequence = -1  # of the last frame estimated
        self._camera_error: CellError | None = None
        self._last_error: CellError | None = None  # why the last frame gave no measurement
        self._thread_error: Exception | None = None
        self._shown_s = 0.0

    def run(self, first: Located | None = None) -> dict[str, Any]:
        """The loop; ``first``: the job's own locate, which the law starts from. Returns the
        fields of its result model (:mod:`cell.results.loop`) that the loop knows."""
        thread = threading.Thread(target=self._frame_thread, daemon=True,
                                  name=f"{self.law.name.lower()}-frames-{self.job_id}")
        with self.lock:  # the clocks start with the loop (the arm is still)
            self.stats.last_s = time.monotonic()
            self._loss.restart(time.monotonic())
        if first is not None:
            self._seed(first)
        thread.start()
        try:
            converged_s = self._control()
        finally:
            self._done.set()
            joined_s = time.monotonic()
            thread.join(timeout=2.0)
        # after the frame thread's end: the result's counts are of the same frames
        out = self._result(converged_s)
        if "phases_s" in out:  # a result that times its phases times the frame thread's end
            out["phases_s"]["frame_thread_join"] = round(time.monotonic() - joined_s, 4)
        return out

    def newest(self) -> M | None:
        with self.lock:
            return self._newest

    def stop(self) -> float:
        settled = self.core.arm.settle(STILL_TIMEOUT_S, self.sc.stop_decel_mm_s2, STILL_POLL_S)
        if settled.refused is not None:
            raise UnavailableError(ErrorCode.arm_disconnected,
                                   f"stopping the arm: {settled.refused}") from settled.refused
        return settled.took_s

    # -- the frame thread ----------------------------------------------------------------------
    def _seed(self, first: Located) -> None:
        self._sequence = first.frame_sequence
        try:
            measurement = self.law.seed(first)
            if measurement is not None:
                self._take(measurement, first)
        except Unusable as why:
            self._unusable(why, first.frame_timestamp_s)

    def _frame_thread(self) -> None:
        try:
            self._frame_loop()
        except Exception as err:  # the control loop sees it and stops the arm
            log.exception("the %s frame thread failed", self.law.name)
            self._thread_error = err

    def _frame_loop(self) -> None:
        locator = self.core.locator
        max_age = self.core.config.limits.max_pose_age_s
        while not self._done.is_set():
            try:
                located = locator.measure(self._sequence, timeout_s=0.5)
            except UnavailableError as err:
                self._camera_error = err
                self._done.wait(0.02)
                continue
            except CellError as err:
                if err.code != "no_new_frame":
                    shown = locator.last_frame  # the frame it was judged on
                    self._unusable(Unusable(err), None if shown is None
                                   or not self.law.blind_frames_examined else shown.timestamp_s)
                continue
            self._camera_error = None
            self._sequence = located.frame_sequence
            if time.monotonic() - located.frame_timestamp_s > max_age:
                self.stats.stale += 1  # never used: what it gives is too old
                self._unusable(Unusable(None, failed=False), located.frame_timestamp_s)
                continue
            try:
                self._take(self.law.read(located), located)
            except Unusable as why:
                self._unusable(why, located.frame_timestamp_s)

    def _take(self, measurement: M, located: Located) -> None:
        with self.lock:
            self.law.admit(measurement)
            self._newest = measurement
            self.stats.taken(located.located_at_s, located.frame_timestamp_s)
            self._loss.pose(located.frame_timestamp_s)

    def _unusable(self, why: Unusable, exposure_s: float | None) -> None:
        """A frame examined that gave no measurement (``exposure_s`` None: not judged)."""
        if why.failed:
            self.stats.failed += 1
        if why.error is not None:
            self._last_error = why.error
        if exposure_s is not None:
            with self.lock:
                self._loss.examined(exposure_s)

    # -- the control loop ----------------------------------------------------------------------
    def _control(self) -> float | None:
        """The loop until it converges (an approach), its duration ends (a track) or it
        fails; the arm stopped and the law's settle made. Returns the time to converge."""
        law, arm, sc = self.law, self.core.arm, self.sc
        clock = TwistClock(arm, sc.tick_s, sc.watchdog_s)
        self.t0 = t0 = time.monotonic()
        seen = -1
        converged_s: float | None = None
        lag = LagWatch(sc.track_lag_mm, sc.track_lag_s) \
            if law.mode == "track" and sc.track_lag_mm > 0 else None
        while True:
            tick = time.monotonic()
            self.motion.raise_if_cancelled(law.doing)
            if self._thread_error is not None:
                self.stop()
                raise RefusedError(ErrorCode.estimator_failed, f"the {law.name} frame thread "
                                   f"failed: {self._thread_error!r}")
            silence, frames, aim = self._aim(tick)
            if aim is None:  # nothing to act on: the target lost, or no measurement yet
                if silence.lost:
                    self._lost(silence)
                time.sleep(sc.tick_s)
                continue
            try:
                state = arm.state()
            except DriverError as err:
                raise UnavailableError(ErrorCode.arm_disconnected,
                                       f"reading the arm: {err}") from err
            T_tcp = clock.tcp_now(state, tick)
            reading = law.judge(aim, T_tcp, frames != seen, tick - t0, clock.prev)
            if reading is not None and frames != seen:
                self._show(reading, tick)
                if lag is not None:
                    behind = lag.over_for_s(tick, reading.errors["error_mm"])
                    if behind is not None:
                        self._fell_behind(reading.errors["error_mm"], behind)
            seen = frames
            if reading is not None and reading.converged:
                converged_s = tick - t0
                break
            if law.mode == "approach" and tick - t0 > law.timeout_s:
                self.stop()
                raise RefusedError(ErrorCode.servo_timeout, f"the {law.name} approach did not "
                                   f"converge within {law.timeout_s} s ({law.left()})")
            if law.mode == "track" and self.duration_s is not None \
                    and tick - t0 >= self.duration_s:
                break
            twist = law.twist(aim, T_tcp, state, tick, clock)
            arm.servo_twist(twist, law.caps.accel_mm_s2, sc.watchdog_s, law.caps.accel_rad_s2)
            clock.sent(twist)
            rest = tick + sc.tick_s - time.monotonic()
            if rest > 0:
                time.sleep(rest)
        self.stop()
        return law.settle(self, converged_s)

    def _aim(self, tick: float) -> tuple[Silence, int, A | None]:
        try:
            with self.lock:
                silence, frames = self._loss.silence(tick), self.stats.frames
                running = self._camera_error is None \
                    and silence.stalled_s < self._loss.stall_after_s
                return silence, frames, self.law.aim(Tick(tick, silence, frames, self._newest,
                                                          running, self._last_error))
        except CellError:
            self.stop()
            raise

    def _show(self, reading: Reading, tick: float) -> None:
        """A new measurement's errors: in the history, a ``servo`` event, and the job's
        progress (every ``PROGRESS_PERIOD_S``, with the recent history the page plots)."""
        t_s = tick - self.t0
        self.history.add(t_s, reading.errors)
        self.core.events.publish("servo", {"job_id": self.job_id, "mode": self.law.event_mode,
                                           "t_s": t_s} | reading.errors)
        if tick - self._shown_s >= PROGRESS_PERIOD_S:
            self._shown_s = tick
            self.core.runner.progress(self.job_id, {"phase": self.law.phase,
                                                    "t_s": round(t_s, 3)} | reading.errors
                                      | reading.shown
                                      | {"recent": self.history.downsampled(PLOT_POINTS,
                                                                            PLOT_POINTS)})

    def _lost(self, silence: Silence) -> None:
        declared_s = time.monotonic()
        took = self.stop()
        why = self._camera_error or self._last_error
        self.core.runner.progress(self.job_id, {"phase": "target_lost",
                                                "stopped_in_ms": round(took * 1000.0, 1),
                                                "lost_at_monotonic_s": declared_s,
                                                "last_pose_exposure_s":
                                                    self._loss.last_pose_exposure_s})
        what = silence.describe(self.sc.lost_after_s, self._loss.stall_after_s, self.law.unseen)
        raise RefusedError(ErrorCode.target_lost, what
                           + (f"; {why.message}" if why is not None else "")
                           + f"; {self.stats.failed} frames without the target, "
                           + self.law.lost_detail(self.stats)
                           + f"; the arm stopped in {took * 1000:.0f} ms")

    def _fell_behind(self, error_mm: float, lag: Lag) -> None:
        took = self.stop()
        self.core.runner.progress(self.job_id, {"phase": "tracking_lag",
                                                "stopped_in_ms": round(took * 1000.0, 1)})
        raise RefusedError(ErrorCode.tracking_lag,
                           f"the arm fell behind the tracked target: {error_mm:.1f} mm from "
                           f"its goal, {lag.rms_mm:.1f} mm RMS over the last "
                           f"{lag.window_s:.2f} s (limit {self.sc.track_lag_mm:g} mm: [servo] "
                           f"track_lag_mm, track_lag_s): the cell cannot keep up; the arm "
                           f"stopped in {took * 1000:.0f} ms")

    def _result(self, converged_s: float | None) -> dict[str, Any]:
        reached = self.core.arm.state().T_base_tcp
        out: dict[str, Any] = {
            "frames": self.stats.frames,
            "failed_frames": self.stats.failed, "stale_frames": self.stats.stale,
            "reached_T_base_tcp": Pose.from_T(reached),
            "pose_latency_ms": ms_stats(self.stats.lags),
            "error_history": self.history.downsampled(),
        } | self.law.result(self, reached)
        if self.law.mode == "approach":
            out.update(converged=True, time_to_converge_s=converged_s)
        else:
            out.update(duration_s=time.monotonic() - self.t0)
        return out
