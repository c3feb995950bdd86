"""The Cell: locate, approach (look-and-move), jog, stop, gripper, status and events.

One object owns the hardware for the service's lifetime. Rules it keeps:
- one motion at a time (approach, jog step or continuous jog); a second one is refused;
- every check runs before anything is commanded, so a refusal means nothing moved;
- stop is always accepted: it cancels the running job or jog and stops the arm now;
- every command is written to the audit log with caller, parameters, outcome and times.
"""

from __future__ import annotations

import logging
import threading
import time
from collections import Counter
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray
from scipy.spatial.transform import Rotation

from cell.config import CellConfig, HandEyeConfig, PoseConfig
from cell.events import EventBus
from cell.frames import CellFrames, approach_tcp, observation_camera, step_goal
from cell.hardware import Hardware, SimWorld
from cell.imagelog import ImageLog
from cell.jobs import Job, JobStore
from cell.locate import Located, Locator
from cell.safety import (
    CellError,
    LimitError,
    NotFoundError,
    RefusedError,
    SafetyGuard,
    UnavailableError,
)
from drivers.arm import ArmState, JogFrame
from drivers.camera import Frame
from drivers.errors import ConnectionLostError, DeviceTimeoutError, DriverError
from drivers.gripper import Gripper
from estimator import PoseResult
from estimator.transforms import make_T, pose_dict, pose_distance, pose_from_T

log = logging.getLogger(__name__)
Matrix4 = NDArray[np.float64]


# A commanded move that has not started within this time has failed. Generous, because a
# loaded host or a busy controller can delay the first motion cycle by a second or more.
START_TIMEOUT_S = 5.0

class Cancelled(CellError):
    """The running motion was cancelled by a stop."""

    kind = "conflict"


def driver_error(err: DriverError, what: str) -> CellError:
    """A hardware error as the cell reports it, the driver's code kept: unavailable when the
    device cannot be reached, otherwise refused in the current state."""
    text = f"{what}: {err}"
    if isinstance(err, ConnectionLostError | DeviceTimeoutError):
        return UnavailableError(err.code, text)
    return RefusedError(err.code, text)


@dataclass
class CellStats:
    """Counters for /metrics; written under the cell's lock."""

    jobs: Counter[str] = field(default_factory=Counter)  # final state -> count
    refusals: Counter[str] = field(default_factory=Counter)  # code -> count
    deadman_stops: int = 0
    stops: int = 0


@dataclass
class Motion:
    """The one motion slot of the cell: who holds it, and how to cancel it."""

    name: str
    cancel: threading.Event
    job_id: str | None = None


@dataclass
class _Jog:
    velocity: NDArray[np.float64]  # [vx, vy, vz mm/s, wx, wy, wz rad/s]
    frame: JogFrame
    last_heartbeat_s: float
    thread: threading.Thread | None = None
    stopped_reason: str = ""


class Cell:
    """The cell service. Thread-safe: the API calls it from many worker threads."""

    def __init__(self, config: CellConfig, hardware: Hardware, jobs: JobStore,
                 image_log: ImageLog | None = None) -> None:
        self.config = config
        self.hw = hardware
        self.jobs = jobs
        self.image_log = image_log
        self.frames = CellFrames(config.hand_eye.T_flange_camera.T(),
                                 config.tool.T_flange_tcp.T())
        self.guard = SafetyGuard(config.limits)
        self.target = config.target.model()
        self.target_centre_mm = self.target.points_mm.mean(axis=0)
        self.events = EventBus()
        self.stats = CellStats()
        self.locator = Locator(config.camera.model(), self.target, hardware.camera,
                               hardware.arm, self.frames, config.camera.fps, image_log)
        self._gripper_lock = threading.Lock()  # one Modbus transaction at a time
        self._gripper_last: dict[str, Any] = {}
        self._lock = threading.RLock()
        self._motion: Motion | None = None
        self._jog: _Jog | None = None
        self._threads: list[threading.Thread] = []
        self._closing = threading.Event()
        self._monitor: threading.Thread | None = None
        self.started_at = time.time()

    @property
    def sim(self) -> SimWorld | None:
        """The simulated world when running on fakes, else None (see cell.hardware)."""
        return self.hw.sim

    # -- lifecycle ------------------------------------------------------------------------
    def start(self) -> None:
        """Connect every device and make the arm ready. The arm does not move."""
        arm = self.hw.arm
        arm.connect()
        arm.power_on()
        arm.set_tcp(self.frames.T_flange_tcp)
        try:
            self.hw.camera.connect()
        except DriverError as err:  # serve anyway: jogging must stay possible without it
            log.warning("camera not available at start: %s", err)
        if self.hw.gripper is not None:
            try:
                self.hw.gripper.connect()
                self.hw.gripper.activate()
            except DriverError as err:
                log.warning("gripper not available at start: %s", err)
        for job_id in self.jobs.recovered:
            log.warning("job %s was interrupted by the previous run; marked interrupted", job_id)
        self._monitor = threading.Thread(target=self._monitor_loop, name="cell-monitor",
                                         daemon=True)
        self._monitor.start()

    def close(self) -> None:
        self._closing.set()
        try:
            self.stop("service", reason="shutdown")
        except Exception:
            log.exception("stop at shutdown failed")
        for t in list(self._threads):
            t.join(timeout=5.0)
        if self._monitor is not None:
            self._monitor.join(timeout=2.0)
        self.hw.close()
        self.jobs.close()

    # -- reads ----------------------------------------------------------------------------
    def arm_state(self) -> ArmState:
        try:
            return self.hw.arm.state()
        except DriverError as err:
            raise driver_error(err, "reading the arm state") from err

    def health(self) -> dict[str, bool]:
        """Whether arm and camera are connected, for the unauthenticated liveness probe.

        An arm that cannot even be read counts as disconnected: the probe must answer
        ``false`` for a dead device rather than fail.
        """
        try:
            arm = bool(self.hw.arm.state().connected)
        except Exception:
            arm = False
        return {"arm_connected": arm, "camera_connected": bool(self.hw.camera.is_connected)}

    def status(self) -> dict[str, Any]:
        now = time.monotonic()
        out: dict[str, Any] = {"state": "idle"}
        try:
            st = self.hw.arm.state()
            out["robot"] = {
                "connected": st.connected, "mode": st.robot_mode, "safety": st.safety_status,
                "moving": st.moving, "protective_stop": st.protective_stop,
                "T_base_tcp": pose_dict(st.T_base_tcp),
                "joints_deg": [float(np.degrees(q)) for q in st.joints_rad],
                "state_age_s": max(0.0, now - st.timestamp_s),
            }
            arm_state = ("disconnected" if not st.connected else
                         "emergency_stop" if st.emergency_stop else
                         "protective_stop" if st.protective_stop else
                         "not_ready" if not st.ready else "idle")
        except DriverError as err:
            out["robot"] = {"connected": False, "error": str(err)}
            arm_state = "disconnected"
        with self._lock:
            motion = self._motion
        last = self.locator.last
        out["state"] = arm_state if arm_state != "idle" or motion is None else motion.name
        cam = self.hw.camera
        frame = self.locator.last_frame
        out["camera"] = {
            "connected": bool(cam.is_connected),
            "last_frame_age_s": None if frame is None else max(0.0, now - frame.timestamp_s),
        }
        out["gripper"] = self._gripper_status()
        job = None
        if motion is not None and motion.job_id is not None:
            j = self.jobs.get(motion.job_id)
            job = None if j is None else j.as_dict()
        out["job"] = job
        out["last_locate"] = None if last is None else last.as_dict(now)
        return out

    def _gripper_status(self) -> dict[str, Any] | None:
        """The gripper's status; while a gripper command holds the serial line, the last one
        read (marked ``stale``) rather than waiting for it."""
        if self.hw.gripper is None:
            return None
        if not self._gripper_lock.acquire(timeout=0.05):
            return {**self._gripper_last, "stale": True}
        try:
            self._gripper_last = self.hw.gripper.status().as_dict()
            return self._gripper_last
        except DriverError as err:
            return {"error": str(err)}
        finally:
            self._gripper_lock.release()

    def job(self, job_id: str) -> Job:
        job = self.jobs.get(job_id)
        if job is None:
            raise NotFoundError("job_not_found", f"no job with id {job_id!r}")
        return job

    def latest_frame(self) -> Frame:
        return self.locator.latest_frame()

    @property
    def last_locate(self) -> Located | None:
        return self.locator.last

    def preview(self, estimate: bool) -> tuple[Frame, PoseResult | None, str | None]:
        return self.locator.preview(estimate)

    # -- audit ----------------------------------------------------------------------------
    @contextmanager
    def _audited(self, caller: str, command: str, params: dict[str, Any]) -> Iterator[
            dict[str, Any]]:
        """Record the command with its outcome; a CellError is logged as a refusal."""
        t0 = time.time()
        note: dict[str, Any] = {"detail": "", "job_id": None}
        try:
            yield note
        except CellError as err:
            with self._lock:
                self.stats.refusals[err.code] += 1
            self.jobs.audit(caller, command, params, f"refused:{err.code}", err.message,
                            note["job_id"], t0)
            raise
        except Exception as err:
            self.jobs.audit(caller, command, params, "error", repr(err), note["job_id"], t0)
            raise
        self.jobs.audit(caller, command, params, "ok", note["detail"], note["job_id"], t0)

    # -- locate ---------------------------------------------------------------------------
    def locate(self, caller: str, n_frames: int = 1) -> Located:
        with self._audited(caller, "locate", {"n_frames": n_frames}) as note:
            loc = self._locate(n_frames)
            note["detail"] = f"rms {loc.result.rms_px:.3f} px"
            return loc

    def _locate(self, n_frames: int = 1, after_s: float | None = None) -> Located:
        loc = self.locator.locate(n_frames, after_s)
        self.events.publish("locate", {"T_base_target": pose_dict(loc.T_base_target),
                                       "rms_px": float(loc.result.rms_px)})
        return loc

    # -- motion bookkeeping ------------------------------------------------------------------
    def count_job_end(self, state: str) -> None:
        """Count a finished job by its end state (for /metrics)."""
        with self._lock:
            self.stats.jobs[state] += 1

    def set_hand_eye(self, T_flange_camera: Matrix4) -> None:
        """Use a new camera mount from now on (after a calibration is applied).

        The last locate is forgotten: it was mapped into the base frame with the old mount.
        """
        position_mm, rotvec_rad = pose_from_T(T_flange_camera)
        pose = PoseConfig(position_mm=(position_mm[0], position_mm[1], position_mm[2]),
                          rotvec_rad=(rotvec_rad[0], rotvec_rad[1], rotvec_rad[2]))
        with self._lock:
            self.frames = CellFrames(np.asarray(T_flange_camera, dtype=float),
                                     self.frames.T_flange_tcp)
            self.config = self.config.model_copy(
                update={"hand_eye": HandEyeConfig(T_flange_camera=pose)})
            self.locator.set_frames(self.frames)

    def claim_motion(self, name: str) -> Motion:
        """Take the cell's single motion slot (RefusedError ``busy`` when it is taken).

        Every task that moves the arm (approach, jog, teach, calibration) holds it, so that
        one motion runs at a time and ``stop`` can cancel whichever it is.
        """
        with self._lock:
            if self._motion is not None:
                raise RefusedError("busy", f"the arm is busy ({self._motion.name}); wait for it "
                                   "to finish or stop it")
            self._motion = Motion(name, threading.Event())
            return self._motion

    def release_motion(self, motion: Motion) -> None:
        with self._lock:
            if self._motion is motion:
                self._motion = None

    def _check_arm(self) -> ArmState:
        st = self.arm_state()
        self.guard.check_arm(st, time.monotonic())
        return st

    def _move(self, T_goal: Matrix4, speed_mm_s: float, accel_mm_s2: float,
              cancel: threading.Event, what: str) -> Matrix4:
        """Linear move with every check first; returns the reached T_base_tcp."""
        st = self._check_arm()
        self.guard.check_goal(st.T_base_tcp, T_goal, what)
        try:
            self.hw.arm.move_linear(T_goal, speed_mm_s, accel_mm_s2, wait=False)
        except DriverError as err:
            raise driver_error(err, f"moving to the {what}") from err
        dist_mm, angle_deg = pose_distance(st.T_base_tcp, T_goal)
        expected_s = dist_mm / speed_mm_s + speed_mm_s / accel_mm_s2 + angle_deg / 20.0
        return self._wait_motion(T_goal, cancel, what, 5.0 + 3.0 * expected_s)

    def _wait_motion(self, T_goal: Matrix4, cancel: threading.Event, what: str,
                     timeout_s: float) -> Matrix4:
        """Poll until the arm rests (not moving, or its pose unchanged for 50 ms: controllers
        may report a residual velocity) and say whether it rests at the goal."""
        t0 = time.monotonic()
        started = False
        still = 0
        prev: Matrix4 | None = None
        while True:
            if cancel.is_set():
                self.stop_arm()
                raise Cancelled("cancelled", f"stopped by request while moving to the {what}")
            st = self.arm_state()
            if st.protective_stop or st.emergency_stop:
                raise RefusedError(
                    "emergency_stop" if st.emergency_stop else "protective_stop",
                    f"the arm stopped on a safety stop ({st.safety_status}) while moving to "
                    f"the {what}")
            if not st.connected:
                raise UnavailableError("arm_disconnected",
                                       f"the arm disconnected while moving to the {what}")
            if prev is not None:
                step_mm, step_deg = pose_distance(prev, st.T_base_tcp)
                still = still + 1 if step_mm < 1e-4 and step_deg < 1e-4 else 0
            prev = st.T_base_tcp
            started = started or (st.moving and still == 0)
            elapsed = time.monotonic() - t0
            if not st.moving or still >= 5:
                d_mm, d_deg = pose_distance(st.T_base_tcp, T_goal)
                if d_mm < 0.2 and d_deg < 0.1:
                    return st.T_base_tcp
                if (started and still >= 5) or elapsed > START_TIMEOUT_S:
                    raise RefusedError("motion_failed", f"the arm stopped {d_mm:.2f} mm / "
                                       f"{d_deg:.2f} deg short of the {what}")
            if elapsed > timeout_s:
                self.stop_arm()
                raise RefusedError("motion_timeout",
                                   f"the move to the {what} took longer than {timeout_s:.1f} s")
            time.sleep(0.01)

    def stop_arm(self) -> str | None:
        """Stop the arm now; the driver's error text if it could not, else None."""
        try:
            self.hw.arm.stop(decel_mm_s2=2000.0)
        except DriverError as err:
            return str(err)
        return None

    # -- approach ---------------------------------------------------------------------------
    def approach(self, caller: str, *, standoff_mm: float | None = None,
                 speed_mm_s: float | None = None, T_target_tcp: Matrix4 | None = None,
                 use_last_locate: bool = False, wait: bool = False,
                 wait_timeout_s: float = 120.0) -> Job:
        """Start a look-and-move approach job; with ``wait`` return when it has ended."""
        ac = self.config.approach
        standoff = ac.standoff_mm if standoff_mm is None else float(standoff_mm)
        speed = ac.speed_mm_s if speed_mm_s is None else float(speed_mm_s)
        accel = min(ac.accel_mm_s2, self.config.limits.max_accel_mm_s2)
        T_tt = ac.T_target_tcp.T() if T_target_tcp is None else np.asarray(T_target_tcp, float)
        params = {"standoff_mm": standoff, "speed_mm_s": speed, "T_target_tcp": pose_dict(T_tt),
                  "use_last_locate": use_last_locate}
        with self._audited(caller, "approach", params) as note:
            if standoff < 0:
                raise LimitError("invalid_standoff", "standoff_mm must not be negative")
            self.guard.check_speed(speed, accel)
            motion = self.claim_motion("approach")
            try:
                st = self._check_arm()
                if not self.hw.camera.is_connected:
                    raise UnavailableError("camera_lost", "the camera is lost: approach needs "
                                           "it (jogging is still possible)")
                if use_last_locate:
                    loc = self.locator.last
                    if loc is None:
                        raise RefusedError("stale_pose", "no target has been located yet")
                    age = time.monotonic() - loc.frame_timestamp_s
                    if age > self.config.limits.max_pose_age_s:
                        raise RefusedError("stale_pose", f"the last located pose is {age:.1f} s "
                                           f"old (limit {self.config.limits.max_pose_age_s} s); "
                                           "locate again")
                else:
                    loc = self._locate(ac.frames_per_locate)
                # Both kinds of goal are checked now so that a refusal moves nothing.
                T_obs = self._observation_tcp(loc.T_base_target, T_tt)
                self.guard.check_goal(st.T_base_tcp, T_obs, "observation pose")
                goal = approach_tcp(loc.T_base_target, T_tt, standoff)
                self.guard.check_goal(T_obs, goal, "approach goal")
                job = self.jobs.create("approach", caller, params)
                motion.job_id = job.id
                note["job_id"] = job.id
            except BaseException:
                self.release_motion(motion)
                raise
            thread = threading.Thread(
                target=self._run_approach, name=f"approach-{job.id}", daemon=True,
                args=(job.id, motion, loc, T_tt, standoff, speed, accel))
            with self._lock:
                self._threads = [t for t in self._threads if t.is_alive()] + [thread]
            thread.start()
        self.events.publish("job", {"job": job.as_dict()})
        if wait:
            thread.join(timeout=wait_timeout_s)
            return self.job(job.id)
        return job

    def _observation_tcp(self, T_base_target: Matrix4, T_target_tcp: Matrix4) -> Matrix4:
        """The TCP already has the goal's orientation, so the final move is a straight
        translation and every cycle sees the target from the same viewpoint."""
        R_tcp = (T_base_target @ T_target_tcp)[:3, :3]
        cam = observation_camera(T_base_target, self.target_centre_mm,
                                 self.config.approach.observe_distance_mm,
                                 R_tcp @ self.frames.T_tcp_camera[:3, :3])
        return self.frames.tcp_for_camera(cam)

    def _run_approach(self, job_id: str, motion: Motion, loc: Located, T_target_tcp: Matrix4,
                      standoff_mm: float, speed_mm_s: float, accel_mm_s2: float) -> None:
        try:
            result = self._look_and_move(job_id, motion, loc, T_target_tcp, standoff_mm,
                                         speed_mm_s, accel_mm_s2)
            job = self.jobs.finish(job_id, "succeeded", result)
        except Cancelled as err:
            job = self.jobs.finish(job_id, "cancelled", None, err.code, err.message)
        except CellError as err:
            self.stop_arm()
            job = self.jobs.finish(job_id, "failed", None, err.code, err.message)
        except Exception as err:
            log.exception("approach job %s crashed", job_id)
            self.stop_arm()
            job = self.jobs.finish(job_id, "failed", None, "internal_error", repr(err))
        finally:
            self.release_motion(motion)
        self.count_job_end(job.state)
        self.jobs.audit(job.caller, "approach_end", {"job_id": job_id}, job.state,
                        job.error_message or "", job_id, job.created_at)
        self.events.publish("job", {"job": job.as_dict()})

    def _look_and_move(self, job_id: str, motion: Motion, loc: Located,
                       T_target_tcp: Matrix4, standoff_mm: float, speed_mm_s: float,
                       accel_mm_s2: float) -> dict[str, Any]:
        ac = self.config.approach
        cycles: list[dict[str, Any]] = []
        converged = False
        goal = approach_tcp(loc.T_base_target, T_target_tcp, standoff_mm)
        for cycle in range(1, ac.max_cycles + 1):
            self.jobs.set_progress(job_id, {"phase": "observe", "cycle": cycle,
                                            "cycles": cycles})
            T_obs = self._observation_tcp(loc.T_base_target, T_target_tcp)
            self._move(T_obs, speed_mm_s, accel_mm_s2, motion.cancel, "observation pose")
            arrived = time.monotonic()
            if ac.settle_s:
                time.sleep(ac.settle_s)
            self.jobs.set_progress(job_id, {"phase": "locate", "cycle": cycle, "cycles": cycles})
            new = self._locate(ac.frames_per_locate, after_s=arrived + ac.settle_s)
            new_goal = approach_tcp(new.T_base_target, T_target_tcp, standoff_mm)
            d_mm, d_deg = pose_distance(goal, new_goal)
            cycles.append({"cycle": cycle, "correction_mm": d_mm, "correction_deg": d_deg,
                           "rms_px": float(new.result.rms_px), "spread_mm": new.spread_mm})
            loc, goal = new, new_goal
            if d_mm < ac.tolerance_mm and d_deg < ac.tolerance_deg:
                converged = True
                break
            if motion.cancel.is_set():
                raise Cancelled("cancelled", "stopped by request between cycles")
        self.jobs.set_progress(job_id, {"phase": "final", "cycle": len(cycles),
                                        "cycles": cycles})
        reached = self._move(goal, speed_mm_s, accel_mm_s2, motion.cancel, "approach goal")
        reach_mm, reach_deg = pose_distance(reached, goal)
        last = cycles[-1]
        return {
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

    # -- jog ----------------------------------------------------------------------------------
    def jog_step(self, caller: str, *, frame: JogFrame, translation_mm: Any,
                 rotation_deg: Any, speed_mm_s: float | None = None) -> Matrix4:
        """A Cartesian step about the TCP in base or tool frame; returns the reached pose."""
        speed = min(self.config.limits.max_jog_speed_mm_s, 50.0) if speed_mm_s is None \
            else float(speed_mm_s)
        accel = min(500.0, self.config.limits.max_accel_mm_s2)
        params = {"frame": frame, "translation_mm": list(map(float, translation_mm)),
                  "rotation_deg": list(map(float, rotation_deg)), "speed_mm_s": speed}
        with self._audited(caller, "jog_step", params):
            limits = self.config.limits
            if not 0 < speed <= limits.max_jog_speed_mm_s:
                raise LimitError("jog_speed_limit", f"jog speed {speed} mm/s is outside (0, "
                                 f"{limits.max_jog_speed_mm_s}]")
            step_mm = float(np.linalg.norm(np.asarray(translation_mm, dtype=float)))
            step_deg = float(np.linalg.norm(np.asarray(rotation_deg, dtype=float)))
            if step_mm > limits.max_jog_step_mm or step_deg > limits.max_jog_step_deg:
                raise LimitError(
                    "jog_step_limit",
                    f"a jog step of {step_mm:.1f} mm / {step_deg:.1f} deg is larger than "
                    f"limits.max_jog_step_mm = {limits.max_jog_step_mm} / max_jog_step_deg = "
                    f"{limits.max_jog_step_deg}: use approach or several steps")
            motion = self.claim_motion("jog_step")
            try:
                st = self._check_arm()
                goal = step_goal(st.T_base_tcp, translation_mm, rotation_deg, frame)
                return self._move(goal, speed, accel, motion.cancel, "jog step")
            finally:
                self.release_motion(motion)

    def jog_start(self, caller: str, *, frame: JogFrame, linear_mm_s: Any,
                  angular_deg_s: Any) -> dict[str, Any]:
        """Start (or change) a continuous jog; it runs while heartbeats keep arriving."""
        lin = np.asarray(linear_mm_s, dtype=float).reshape(3)
        ang = np.asarray(angular_deg_s, dtype=float).reshape(3)
        params = {"frame": frame, "linear_mm_s": lin.tolist(), "angular_deg_s": ang.tolist()}
        with self._audited(caller, "jog_start", params):
            self.guard.check_jog_speed(lin, ang)
            velocity = np.concatenate([lin, np.radians(ang)])
            with self._lock:
                jog = self._jog
                if jog is not None and self._motion is not None and self._motion.name == "jog":
                    jog.velocity, jog.frame = velocity, frame
                    jog.last_heartbeat_s = time.monotonic()
                    return self._jog_info(jog)
            motion = self.claim_motion("jog")
            try:
                self._check_arm()
            except BaseException:
                self.release_motion(motion)
                raise
            jog = _Jog(velocity, frame, time.monotonic())
            jog.thread = threading.Thread(target=self._jog_loop, args=(motion, jog),
                                          name="cell-jog", daemon=True)
            with self._lock:
                self._jog = jog
            jog.thread.start()
            self.events.publish("jog", {"jogging": True, **params})
            return self._jog_info(jog)

    def heartbeat(self, caller: str) -> dict[str, Any]:
        """Dead-man: keeps a continuous jog alive for ``limits.deadman_timeout_s`` more."""
        _ = caller
        with self._lock:
            jog = self._jog
            if jog is None or self._motion is None or self._motion.name != "jog":
                raise RefusedError("not_jogging", "no continuous jog is running (it may have "
                                   "stopped: dead-man expired, stop, or a limit)")
            jog.last_heartbeat_s = time.monotonic()
            return self._jog_info(jog)

    def _jog_info(self, jog: _Jog) -> dict[str, Any]:
        return {"jogging": True, "frame": jog.frame,
                "deadman_timeout_s": self.config.limits.deadman_timeout_s}

    def _jog_loop(self, motion: Motion, jog: _Jog) -> None:
        limits = self.config.limits
        period_s = 0.02
        reason = "stopped"
        try:
            while True:
                if motion.cancel.is_set():
                    reason = "stop requested"
                    break
                if time.monotonic() - jog.last_heartbeat_s > limits.deadman_timeout_s:
                    reason = "dead-man: heartbeat expired"
                    with self._lock:
                        self.stats.deadman_stops += 1
                    break
                st = self.hw.arm.state()
                if not st.ready:
                    reason = f"arm not ready ({st.safety_status})"
                    break
                if not self.guard.jog_allowed(st.T_base_tcp, self._jog_ahead(st.T_base_tcp,
                                                                              jog, 0.15)):
                    reason = "limit: the jog would leave the workspace or tilt limit"
                    break
                self.hw.arm.jog(jog.velocity, jog.frame,
                                accel_mm_s2=min(500.0, limits.max_accel_mm_s2))
                time.sleep(period_s)
        except DriverError as err:
            reason = f"arm error: {err}"
        finally:
            self.stop_arm()
            jog.stopped_reason = reason
            with self._lock:
                if self._jog is jog:
                    self._jog = None
            self.release_motion(motion)
            self.jobs.audit("service", "jog_end", {}, "stopped", reason)
            self.events.publish("jog", {"jogging": False, "reason": reason})

    @staticmethod
    def _jog_ahead(T: Matrix4, jog: _Jog, horizon_s: float) -> Matrix4:
        v, w = jog.velocity[:3], jog.velocity[3:]
        dR = Rotation.from_rotvec(w * horizon_s).as_matrix()
        if jog.frame == "tool":
            return make_T(T[:3, :3] @ dR, T[:3, 3] + T[:3, :3] @ v * horizon_s)
        return make_T(dR @ T[:3, :3], T[:3, 3] + v * horizon_s)

    # -- stop --------------------------------------------------------------------------------
    def stop(self, caller: str, reason: str = "requested") -> dict[str, Any]:
        """Always accepted: cancel the running job or jog and stop the arm now."""
        t0 = time.time()
        with self._lock:
            motion = self._motion
            if motion is not None:
                motion.cancel.set()
            self.stats.stops += 1
        arm_error = self.stop_arm()
        job_id = None if motion is None else motion.job_id
        out = {"stopped": arm_error is None, "cancelled": None if motion is None else motion.name,
               "job_id": job_id, "arm_error": arm_error}
        self.jobs.audit(caller, "stop", {"reason": reason}, "ok" if arm_error is None else
                        "arm_error", arm_error or "", job_id, t0)
        self.events.publish("stop", out)
        return out

    # -- gripper -----------------------------------------------------------------------------
    def gripper(self, caller: str, action: str, position_mm: float | None = None,
                speed_pct: float = 100.0, force_pct: float = 50.0,
                wait: bool = True) -> dict[str, Any]:
        params = {"action": action, "position_mm": position_mm, "speed_pct": speed_pct,
                  "force_pct": force_pct, "wait": wait}
        with self._audited(caller, "gripper", params):
            g = self.hw.gripper
            if g is None:
                raise UnavailableError("gripper_unavailable", "this cell has no gripper")
            with self._gripper_lock:
                return self._gripper_command(g, action, position_mm, speed_pct, force_pct, wait)

    @staticmethod
    def _gripper_command(g: Gripper, action: str, position_mm: float | None, speed_pct: float,
                         force_pct: float, wait: bool) -> dict[str, Any]:
        try:
            if action == "open":
                st = g.open(wait=wait)
            elif action == "close":
                st = g.close(wait=wait)
            elif action == "activate":
                st = g.activate()
            elif action == "move":
                if position_mm is None:
                    raise LimitError("invalid_request", "move needs position_mm")
                st = g.move(position_mm, speed_pct, force_pct, wait=wait)
            else:
                raise LimitError("invalid_request", f"unknown gripper action {action!r}")
        except DriverError as err:
            raise driver_error(err, f"gripper {action}") from err
        return st.as_dict()

    # -- events ------------------------------------------------------------------------------
    def _monitor_loop(self) -> None:
        """Publish pose and state at camera rate while anyone listens."""
        period = 1.0 / min(self.config.camera.fps, 30.0)
        while not self._closing.wait(period):
            if self.events.n_subscribers == 0:
                continue
            try:
                st = self.hw.arm.state()
            except DriverError:
                continue
            with self._lock:
                motion = self._motion
            self.events.publish("state", {
                "state": motion.name if motion else "idle",
                "robot_mode": st.robot_mode, "safety": st.safety_status, "moving": st.moving,
                "T_base_tcp": pose_dict(st.T_base_tcp),
                "job_id": motion.job_id if motion else None,
                "camera_connected": bool(self.hw.camera.is_connected),
            })
