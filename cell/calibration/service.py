"""The hand-eye routine as a job of the running cell, for the HTTP API and the operator page.

The routine (cell.calibration.routine) drives the arm directly; here it runs on the cell's own
arm and camera under the cell's rules:
- it holds the cell's motion slot for its whole run, so no approach or jog can interleave and
  ``stop`` cancels it like any other motion;
- every view pose passes the cell's safety checks before it is commanded (a view outside the
  envelope or tilt limit is skipped, not moved to), and nothing moves after a stop: not even
  the routine's return to its start pose;
- progress goes to the job record and to the event bus (``calibration`` events);
- the result changes nothing until someone asks: ``apply`` puts it into the running cell's
  frame chain and, if asked, into the config file's ``[hand_eye]`` table.
"""

from __future__ import annotations

import logging
import threading
import time
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from cell.calibration.config_writer import ConfigWriteError, write_hand_eye
from cell.calibration.dataset import DatasetError
from cell.calibration.observe import dot_target_observer
from cell.calibration.routine import (
    RoutineError,
    RoutineResult,
    RoutineSettings,
    run_hand_eye_routine,
    save_views,
)
from cell.calibration.solve import CHOICES
from cell.jobs import Job
from cell.safety import CellError, LimitError, NotFoundError, RefusedError, UnavailableError
from cell.service import Cancelled, Cell, Motion, driver_error
from drivers.arm import Arm
from drivers.errors import DriverError, MotionError
from estimator.transforms import T_from_pose_dict, pose_dict, pose_distance

log = logging.getLogger(__name__)
Matrix4 = NDArray[np.float64]

JOB_KIND = "hand_eye_calibration"
EVENT = "calibration"


class _GuardedArm:
    """The cell's arm as the routine sees it: moves are checked by the cell's safety guard
    first, and refused for good once the job is cancelled (so a stop really stops)."""

    def __init__(self, cell: Cell, cancel: threading.Event) -> None:
        self._cell = cell
        self._arm = cell.hw.arm
        self._cancel = cancel

    def __getattr__(self, name: str) -> Any:
        return getattr(self._arm, name)

    def move_linear(self, T_base_tcp: Matrix4, speed_mm_s: float, accel_mm_s2: float,
                    wait: bool = True) -> None:
        if self._cancel.is_set():
            raise Cancelled("cancelled", "stopped by request during the calibration")
        try:
            self._cell.guard.check_goal(self._arm.tcp_pose(), T_base_tcp, "calibration view")
        except LimitError as err:
            raise MotionError(err.message) from err  # the routine skips this view
        self._arm.move_linear(T_base_tcp, speed_mm_s, accel_mm_s2, wait)
        if self._cancel.is_set():
            raise Cancelled("cancelled", "stopped by request during the calibration")


class CalibrationService:
    """Hand-eye calibration jobs on one cell; ``config_path`` is the file ``apply`` may write
    (None: the cell runs a built-in config, and writing is refused)."""

    def __init__(self, cell: Cell, config_path: str | Path | None = None) -> None:
        self.cell = cell
        self.config_path = None if config_path is None else Path(config_path)
        self._threads: list[threading.Thread] = []

    # -- start -------------------------------------------------------------------------------
    def start(self, caller: str, settings: RoutineSettings) -> Job:
        """Start the routine around the arm's current pose; returns the running job."""
        cell = self.cell
        limits = cell.config.limits
        params = {"views": settings.n_views, "tilt_deg": settings.tilt_deg,
                  "roll_deg": settings.roll_deg, "speed_mm_s": settings.speed_mm_s,
                  "method": settings.chosen}
        t0 = time.time()
        try:
            if settings.chosen not in CHOICES:
                raise LimitError("invalid_request", f"method must be one of {', '.join(CHOICES)}")
            cell.guard.check_speed(settings.speed_mm_s,
                                   min(settings.accel_mm_s2, limits.max_accel_mm_s2))
            motion = cell.claim_motion("calibration")
            try:
                cell.guard.check_arm(cell.arm_state(), time.monotonic())
                if not cell.hw.camera.is_connected:
                    raise UnavailableError("camera_lost", "calibration needs the camera")
                job = cell.jobs.create(JOB_KIND, caller, params)
                motion.job_id = job.id
            except BaseException:
                cell.release_motion(motion)
                raise
        except CellError as err:
            cell.jobs.audit(caller, "calibrate", params, f"refused:{err.code}", err.message,
                            None, t0)
            raise
        cell.jobs.audit(caller, "calibrate", params, "ok", "started", job.id, t0)
        thread = threading.Thread(target=self._run, args=(job.id, motion, settings),
                                  name=f"calibration-{job.id}", daemon=True)
        self._threads = [t for t in self._threads if t.is_alive()] + [thread]
        thread.start()
        self._publish(job)
        return job

    def _run(self, job_id: str, motion: Motion, settings: RoutineSettings) -> None:
        cell = self.cell
        guess = cell.frames.T_flange_camera

        def progress(stage: str, done: int, total: int) -> None:
            info = {"stage": stage, "done": done, "total": total}
            cell.jobs.set_progress(job_id, info)
            cell.events.publish(EVENT, {"job_id": job_id, "state": "running", **info})

        try:
            progress("views", 0, settings.n_views)
            arm: Arm = _GuardedArm(cell, motion.cancel)
            result = run_hand_eye_routine(
                arm, cell.hw.camera, dot_target_observer(cell.target),
                cell.frames.T_flange_tcp, guess, settings, progress)
            report = result.report
            out = report.as_dict()
            out["failed_views"] = [{"view": k, "reason": r} for k, r in result.failed]
            d_mm, d_deg = pose_distance(report.T_flange_camera, guess)
            out["change_from_current"] = {"T_flange_camera": pose_dict(guess),
                                          "distance_mm": d_mm, "distance_deg": d_deg}
            out["applied"] = None
            out["dataset"] = self._save(job_id, result)
            job = cell.jobs.finish(job_id, "succeeded", out)
        except Cancelled as err:
            job = cell.jobs.finish(job_id, "cancelled", None, err.code, err.message)
        except RoutineError as err:
            job = cell.jobs.finish(job_id, "failed", None, err.code, err.message)
        except DriverError as err:
            cell.stop_arm()
            e = driver_error(err, "calibration")
            job = cell.jobs.finish(job_id, "failed", None, e.code, e.message)
        except Exception as err:
            log.exception("calibration job %s crashed", job_id)
            cell.stop_arm()
            job = cell.jobs.finish(job_id, "failed", None, "internal_error", repr(err))
        finally:
            cell.release_motion(motion)
        cell.count_job_end(job.state)
        cell.jobs.audit(job.caller, "calibrate_end", {"job_id": job_id}, job.state,
                        job.error_message or "", job_id, job.created_at)
        self._publish(job)

    def _save(self, job_id: str, result: RoutineResult) -> dict[str, Any] | None:
        """Save the views as a dataset (see ``[api] calibration_dir``) -> where, or why not.

        A failure to save does not fail the calibration, whose result stands on its own; it
        is reported in the result and logged."""
        root = self.cell.config.api.calibration_dir
        if not root:
            return None
        folder = Path(root) / f"hand-eye-{job_id}"
        try:
            dataset = save_views(folder, result, self.cell.target)
        except (DatasetError, OSError) as err:
            log.warning("calibration job %s: views not saved to %s: %s", job_id, folder, err)
            return {"folder": str(folder), "saved": False, "error": str(err)}
        return {"folder": str(dataset.folder), "saved": True, "views": len(dataset.views)}

    def _publish(self, job: Job) -> None:
        self.cell.events.publish(EVENT, {"job_id": job.id, "state": job.state,
                                         **job.progress, "job": job.as_dict()})
        self.cell.events.publish("job", {"job": job.as_dict()})

    # -- read --------------------------------------------------------------------------------
    def job(self, job_id: str) -> Job:
        job = self.cell.jobs.get(job_id)
        if job is None or job.kind != JOB_KIND:
            raise NotFoundError("job_not_found", f"no hand-eye calibration job {job_id!r}")
        return job

    def wait(self, job_id: str, timeout_s: float) -> Job:
        deadline = time.monotonic() + timeout_s
        job = self.job(job_id)
        while not job.finished and time.monotonic() < deadline:
            time.sleep(0.05)
            job = self.job(job_id)
        return job

    # -- apply -------------------------------------------------------------------------------
    def apply(self, caller: str, job_id: str, method: str | None = None,
              running: bool = True, write_config: bool = False,
              force: bool = False) -> dict[str, Any]:
        """Use a finished job's ``T_flange_camera`` (its chosen method unless ``method``):
        in the running cell (``running``) and/or the config file (``write_config``).

        Refused while the arm moves (a look-and-move must not change frames mid-way) and, unless
        ``force``, when the job's verdict says its data disagree with themselves.
        """
        params = {"job_id": job_id, "method": method, "running": running,
                  "write_config": write_config, "force": force}
        t0 = time.time()
        cell = self.cell
        try:
            T = self._result_T(self.job(job_id), method, force)
            if not running and not write_config:
                raise LimitError("invalid_request", "nothing to do: ask for running and/or "
                                 "write_config")
            if write_config and self.config_path is None:
                raise RefusedError("no_config_file", "the cell runs a built-in config; start it "
                                   "with a config file (CELL_CONFIG) to write the result")
            motion = cell.claim_motion("apply_calibration")
            change = None
            try:
                if write_config:
                    assert self.config_path is not None
                    try:
                        change = write_hand_eye(self.config_path, T,
                                                f"hand-eye calibration job {job_id} by {caller}")
                    except ConfigWriteError as err:
                        raise RefusedError(err.code, str(err)) from err
                if running:
                    cell.set_hand_eye(T)
            finally:
                cell.release_motion(motion)
        except CellError as err:
            cell.jobs.audit(caller, "apply_calibration", params, f"refused:{err.code}",
                            err.message, job_id, t0)
            raise
        out = {"job_id": job_id, "T_flange_camera": pose_dict(T), "running": running,
               "written_config": str(self.config_path) if write_config else None,
               # the old and new mount and the timestamped backup of the old file
               "config_change": None if change is None else change.as_dict()}
        cell.jobs.audit(caller, "apply_calibration", params, "ok", "", job_id, t0)
        cell.events.publish(EVENT, {"job_id": job_id, "state": "applied", "applied": out})
        return out

    @staticmethod
    def _result_T(job: Job, method: str | None, force: bool) -> Matrix4:
        if job.state != "succeeded" or job.result is None:
            raise RefusedError("job_not_succeeded", f"calibration job {job.id} is {job.state}; "
                               "only a succeeded job can be applied")
        r = job.result
        if not r["verdict"]["consistent"] and not force:
            raise RefusedError("calibration_inconsistent", "the calibration data disagree with "
                               f"themselves ({r['verdict']['text']}); apply with force=true only "
                               "if you accept that")
        if method is None or method == r["chosen"]:
            return T_from_pose_dict(r["T_flange_camera"])
        if method == "joint":
            if r.get("joint") is None:
                raise NotFoundError("method_not_found", "this job has no joint refinement")
            return T_from_pose_dict(r["joint"]["T_flange_camera"])
        if method not in r["methods"]:
            raise NotFoundError("method_not_found", f"no result for method {method!r}; have "
                                f"{', '.join([*r['methods'], 'joint'])}")
        return T_from_pose_dict(r["methods"][method]["T_flange_camera"])

