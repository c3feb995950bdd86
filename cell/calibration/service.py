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
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from cell.calibration.config_writer import ConfigWriteError, write_hand_eye
from cell.calibration.dataset import DatasetError
from cell.calibration.observe import dot_target_observer
from cell.calibration.report import mount_fields
from cell.calibration.routine import (
    RoutineError,
    RoutineResult,
    RoutineSettings,
    run_hand_eye_routine,
    save_views,
)
from cell.calibration.solve import CHOICES
from cell.core import CellCore
from cell.error_codes import ErrorCode
from cell.errors import LimitError, NotFoundError, RefusedError, UnavailableError
from cell.jobs.store import Job
from cell.motion.guard import Motion
from cell.results.calibration import CalibrationApplied
from cell.results.pose import Pose
from cell.results.routine import FailedView, HandEyeRoutineResult, MountChange, SavedViews
from cell.supervision.dataset_retention import dataset_folder_name
from estimator.kinematics import UR_DH
from estimator.transforms import pose_distance

log = logging.getLogger(__name__)
Matrix4 = NDArray[np.float64]

JOB_KIND = "hand_eye_calibration"
EVENT = "calibration"


class CalibrationService:
    """Hand-eye calibration jobs on one cell (its shared parts, ``core``); ``set_hand_eye``
    puts an applied mount into the running cell (``Cell.set_hand_eye``); ``config_path`` is
    the file ``apply`` may write (None: the cell runs a built-in config, and writing is
    refused)."""

    def __init__(self, core: CellCore, set_hand_eye: Callable[[Matrix4], None],
                 config_path: str | Path | None = None) -> None:
        self.core = core
        self._set_hand_eye = set_hand_eye
        self.config_path = None if config_path is None else Path(config_path)

    # -- start -------------------------------------------------------------------------------
    def start(self, caller: str, settings: RoutineSettings) -> Job:
        """Start the routine around the arm's current pose; returns the running job."""
        core = self.core
        params = {"views": settings.n_views, "tilt_deg": settings.tilt_deg,
                  "roll_deg": settings.roll_deg, "speed_mm_s": settings.speed_mm_s,
                  "method": settings.chosen}

        def check(motion: Motion) -> None:
            if settings.chosen not in CHOICES:
                raise LimitError(ErrorCode.invalid_request,
                                 f"method must be one of {', '.join(CHOICES)}")
            core.arm.guard.check_speed(settings.speed_mm_s, settings.accel_mm_s2)
            core.arm.ready_state()
            if not core.camera.is_connected:
                raise UnavailableError(ErrorCode.camera_lost, "calibration needs the camera")

        def work(job_id: str, motion: Motion) -> HandEyeRoutineResult:
            return self._run(job_id, settings)

        return core.runner.start(JOB_KIND, caller, params, work, check=check, needs_camera=True,
                                 on_change=self._publish, motion_name="calibration")

    def _run(self, job_id: str, settings: RoutineSettings) -> HandEyeRoutineResult:
        core = self.core
        fixed = core.frames.is_fixed
        guess = core.frames.T_camera_mount  # T_base_camera for a fixed camera

        def progress(stage: str, done: int, total: int) -> None:
            info = {"stage": stage, "done": done, "total": total}
            core.runner.progress(job_id, info)
            core.events.publish(EVENT, {"job_id": job_id, "state": "running", **info})

        progress("views", 0, settings.n_views)
        try:
            result = run_hand_eye_routine(
                core.arm, core.camera, dot_target_observer(core.target),
                core.frames.T_flange_tcp, guess, settings, progress, fixed_camera=fixed,
                intrinsics=core.locator.intrinsics.model_for,
                arm_geometry=UR_DH[core.config.robot.model])
        except RoutineError as err:
            raise RefusedError(ErrorCode(err.code), err.message) from err
        report = result.report
        mount = mount_fields(fixed, report.T_flange_camera)
        d_mm, d_deg = pose_distance(report.T_flange_camera, guess)
        return HandEyeRoutineResult(
            **report.solution().set_values(), **mount.set_values(),
            failed_views=[FailedView(view=k, reason=r) for k, r in result.failed],
            change_from_current=MountChange(**{mount.transform: Pose.from_T(guess)},
                                            distance_mm=d_mm, distance_deg=d_deg),
            applied=None, dataset=self._save(job_id, result))

    def _save(self, job_id: str, result: RoutineResult) -> SavedViews | None:
        """Save the views as a dataset (see ``[api] calibration_dir``) -> where, or why not.

        A failure to save does not fail the calibration, whose result stands on its own; it
        is reported in the result and logged."""
        root = self.core.config.api.calibration_dir
        if not root:
            return None
        folder = Path(root) / dataset_folder_name(job_id)
        try:
            dataset = save_views(folder, result, self.core.target,
                                 self.core.config.robot.model)
        except (DatasetError, OSError) as err:
            log.warning("calibration job %s: views not saved to %s: %s", job_id, folder, err)
            return SavedViews(folder=str(folder), saved=False, error=str(err))
        return SavedViews(folder=str(dataset.folder), saved=True, views=len(dataset.views))

    def _publish(self, job: Job) -> None:
        self.core.events.publish(EVENT, {"job_id": job.id, "state": job.state,
                                         **job.progress, "job": job.as_dict()})

    # -- read --------------------------------------------------------------------------------
    def job(self, job_id: str) -> Job:
        job = self.core.jobs.get(job_id)
        if job is None or job.kind != JOB_KIND:
            raise NotFoundError(ErrorCode.job_not_found, f"no hand-eye calibration job {job_id!r}")
        return job

    def datasets_in_use(self, audit_rows: int = 1000) -> set[str]:
        """The dataset folder of the calibration applied last (from the newest ``audit_rows``
        rows of the audit log; none when the config file's calibration was never replaced)."""
        applied = next((e for e in self.core.jobs.audit_log(audit_rows)
                        if e.command == "apply_calibration" and e.outcome == "ok"
                        and (e.params.get("running") or e.params.get("write_config"))), None)
        if applied is None or not applied.params.get("job_id"):
            return set()
        return {dataset_folder_name(str(applied.params["job_id"]))}

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
              force: bool = False) -> CalibrationApplied:
        """Use a finished job's ``T_flange_camera`` (its chosen method unless ``method``;
        ``T_base_camera`` for a fixed camera, in the ``[hand_eye]`` key of that name):
        in the running cell (``running``) and/or the config file (``write_config``).

        Refused while the arm moves (a look-and-move must not change frames mid-way) and, unless
        ``force``, when the job's verdict says its data disagree with themselves.
        """
        params = {"job_id": job_id, "method": method, "running": running,
                  "write_config": write_config, "force": force}
        core = self.core
        with core.audit.command(caller, "apply_calibration", params) as note:
            note.job_id = job_id
            T = self._result_T(self.job(job_id), method, force)
            if not running and not write_config:
                raise LimitError(ErrorCode.invalid_request, "nothing to do: ask for running and/or "
                                 "write_config")
            if write_config and self.config_path is None:
                raise RefusedError(ErrorCode.no_config_file,
                                   "the cell runs a built-in config; start it "
                                   "with a config file (CELL_CONFIG) to write the result")
            change = None
            with core.slot.hold("apply_calibration"):
                if write_config:
                    assert self.config_path is not None
                    try:
                        change = write_hand_eye(self.config_path, T,
                                                f"hand-eye calibration job {job_id} by {caller}")
                    except ConfigWriteError as err:
                        raise RefusedError(ErrorCode(err.code), str(err)) from err
                if running:
                    self._set_hand_eye(T)
        out = CalibrationApplied(
            job_id=job_id, T_flange_camera=Pose.from_T(T),
            **mount_fields(core.frames.is_fixed, T).set_values(), running=running,
            written_config=str(self.config_path) if write_config else None,
            config_change=None if change is None else change.record())
        core.events.publish(EVENT, {"job_id": job_id, "state": "applied",
                                    "applied": out.json_dict()})
        return out

    @staticmethod
    def _result_T(job: Job, method: str | None, force: bool) -> Matrix4:
        r = job.result
        if job.state != "succeeded" or not isinstance(r, HandEyeRoutineResult):
            raise RefusedError(ErrorCode.job_not_succeeded,
                               f"calibration job {job.id} is {job.state}; "
                               "only a succeeded job can be applied")
        if not r.verdict.consistent and not force:
            raise RefusedError(ErrorCode.calibration_inconsistent,
                               "the calibration data disagree with "
                               f"themselves ({r.verdict.text}); apply with force=true only "
                               "if you accept that")
        if method is None or method == r.chosen:
            return r.T_flange_camera.T()
        if method == "kinematic":
            if r.kinematic is None:
                raise NotFoundError(ErrorCode.method_not_found,
                                    "this job has no kinematic fit (it needs the joints of at "
                                    "least 16 views of a camera on the hand)")
            return r.kinematic.T_flange_camera.T()
        if method in ("joint", "hybrid"):
            refined = r.joint if method == "joint" else r.hybrid
            if refined is None:
                raise NotFoundError(ErrorCode.method_not_found,
                                    f"this job has no {method} refinement")
            return refined.T_flange_camera.T()
        if method not in r.methods:
            raise NotFoundError(ErrorCode.method_not_found,
                                f"no result for method {method!r}; have "
                                f"{', '.join([*r.methods, 'joint', 'hybrid'])}")
        return r.methods[method].T_flange_camera.T()

