"""The Cell: a small facade over the cell's modules, for the API and the CLI.

One object owns the hardware for the service's lifetime; the work is done by the modules it
wires together, each with one responsibility:

- :mod:`cell.motion`: the one guarded path to the arm and the one-motion-at-a-time slot;
- :mod:`cell.jobs`: the lifecycle of every job, the audit log, the events;
- :mod:`cell.actions`: what moves the arm (approach, track and its servo, jog, recovery, stop);
- :mod:`cell.vision`: the frame chain and locate;
- :mod:`cell.supervision`: devices that drop and come back, what is reported, the gripper;
- :mod:`cell.features`: the taught poses, the recipes, the alarms, the camera settings;
- :mod:`cell.calibration`: the hand-eye routine as a job, and applying its result.

The stores live here, built once with the cell and closed with it, so every interface (HTTP,
OPC UA, Modbus, XML-RPC) reads and writes the same ones: ``taught``, ``recipes``,
``alarms``, ``calibration``, the calibration ``reference`` and its ``checks``.

docs/architecture.md draws the whole house.

Rules: one motion at a time; every check before anything is commanded (a refusal moves
nothing); stop is always accepted and cancels whatever holds the motion slot; every command is
in the audit log.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from cell.actions import approach as approach_mod
from cell.actions import pick as pick_mod
from cell.actions import recovery, track
from cell.actions.jog import Jogger
from cell.actions.stop import StopLine
from cell.calibration.check import CalibrationCheck, ReferenceStore
from cell.calibration.schedule import CheckSchedule
from cell.calibration.service import CalibrationService
from cell.config.schema import CellConfig, HandEyeConfig, PoseConfig
from cell.core import CellCore
from cell.devices.hardware import Hardware, SimWorld
from cell.error_codes import ErrorCode
from cell.errors import CellError, LimitError, NotFoundError, RefusedError
from cell.features.alarms import AlarmLog
from cell.features.camera_control import apply_camera_settings, camera_settings
from cell.features.recipes import RecipeStore
from cell.features.teach import (
    DEFAULT_MAX_SPREAD_DEG,
    DEFAULT_MAX_SPREAD_MM,
    TaughtFrame,
    TaughtPose,
    TaughtStore,
    teach,
)
from cell.jobs.audit import Auditor
from cell.jobs.events import EventBus
from cell.jobs.runner import JobRunner
from cell.jobs.store import Job, JobStore
from cell.motion.guard import GuardedArm, MotionSlot, driver_error
from cell.results.modes import ApproachMode
from cell.servoing.ibvs import Features
from cell.stats import CellStats
from cell.supervision.gripper import GripperService
from cell.supervision.host_watch import HostWatch
from cell.supervision.links import LinkSupervisor
from cell.supervision.retention import Retention
from cell.supervision.snapshot import CellSnapshot
from cell.supervision.stall_traces import StallTraces
from cell.supervision.startup import Startup
from cell.supervision.storage import StorageWatch, state_dirs, stop_unrecordable_jobs
from cell.vision.frames import CellFrames, cell_frames
from cell.vision.imagelog import ImageLog
from cell.vision.locate import IN_USE, Located, Locator
from cell.vision.parts import LocatedParts
from drivers.arm import ArmState, JogFrame
from drivers.camera import FocusSetting, Frame
from drivers.errors import DriverError
from estimator import PoseResult, Target
from estimator.transforms import pose_from_T

log = logging.getLogger(__name__)
Matrix4 = NDArray[np.float64]


class Cell:
    """The cell service. Thread-safe: the API calls it from many worker threads.

    ``config_path``: the file ``config`` was read from, which an applied calibration may
    rewrite (None: a built-in config, and writing it is refused)."""

    def __init__(self, config: CellConfig, hardware: Hardware, jobs: JobStore,
                 image_log: ImageLog | None = None,
                 config_path: str | Path | None = None,
                 stall_traces: Path | None = None) -> None:
        """``stall_traces``: the file where the host watch writes every thread's stack when
        the service stands still for seconds (``cell serve``: ``stall-traces.txt`` beside the
        job database; cell.supervision.stall_traces)."""
        self.config = config
        self.hw = hardware
        self.jobs = jobs
        self.image_log = image_log
        self.events = EventBus()
        self.stats = CellStats()
        slot = MotionSlot()
        arm = GuardedArm(hardware.arm, config.limits, slot, model=config.robot.model)
        frames = cell_frames(config)
        target = config.target.model()
        locator = Locator(config.camera.model(), target, hardware.camera, arm, frames,
                          config.camera.fps, image_log, config.camera.intrinsics,
                          config.locate.order, config.locate.same_part_mm)
        audit = Auditor(jobs, self.stats)
        self.host_watch = HostWatch(
            traces=None if stall_traces is None else StallTraces(stall_traces))
        runner = JobRunner(jobs, slot, arm, self.events, audit, self.stats,
                           host_note=self.host_watch.note)
        self.core = CellCore(config, hardware, arm, slot, jobs, self.events, audit, runner,
                             locator, self.stats, frames, target)
        self.startup = Startup()  # what of the start still runs behind a serving API
        self.links = LinkSupervisor(self.core, self.startup)
        self.gripper_ops = GripperService(hardware.gripper, audit, self.events, slot, arm.gate,
                                          self.startup, host_note=self.host_watch.note)
        self.stopper = StopLine(self.core, self.gripper_ops.halt)
        self.jogger = Jogger(self.core, self.stopper.stop)
        self.storage = StorageWatch(jobs, state_dirs(jobs, config.api.calibration_dir,
                                                     config.api.image_log_dir),
                                    busy=lambda: slot.current is not None)
        stop_unrecordable_jobs(jobs, slot, self.stopper.submit)
        # more /health reasons from outside the cell (the PLC servers that cannot listen)
        self.health_reasons: list[Callable[[], list[dict[str, str]]]] = []
        self.snapshot = CellSnapshot(self.core, self.links, self.gripper_ops, self.storage,
                                     starting=lambda: self.startup.active,
                                     reason_sources=self.health_reasons)
        self.taught = TaughtStore.beside_job_db(config.api.job_db)
        self.recipes = RecipeStore.beside_job_db(config.api.job_db, config.limits)
        self.alarms = AlarmLog(jobs, self.events, self.status,
                               starting=lambda: self.startup.active)
        self.calibration = CalibrationService(self.core, self.set_hand_eye, config_path)
        self.reference = ReferenceStore.beside_job_db(config.api.job_db)
        self.checks = CalibrationCheck(self.core, self.reference)
        self.check_schedule = CheckSchedule(self.checks)
        self.retention = Retention(
            config.retention, jobs, self.alarms.prune, image_log,
            idle=lambda: slot.current is None,
            datasets=Path(config.api.calibration_dir) if config.api.calibration_dir else None,
            datasets_in_use=self.calibration.datasets_in_use)
        self.started_at = time.time()

    # -- what other modules read ---------------------------------------------------------------
    @property
    def sim(self) -> SimWorld | None:
        """The simulated world when running on fakes, else None (see cell.devices.hardware)."""
        return self.hw.sim

    @property
    def arm(self) -> GuardedArm:
        return self.core.arm

    @property
    def locator(self) -> Locator:
        return self.core.locator

    @property
    def frames(self) -> CellFrames:
        return self.core.frames

    @property
    def target(self) -> Any:
        return self.core.target

    # -- lifecycle ------------------------------------------------------------------------
    def start(self, connect_in_background: bool = False) -> None:
        """Connect what is reachable and serve; the rest is retried in the background.
        The arm does not move (it is told to stop, and powered on only if configured).
        ``connect_in_background``: return before the first connect (and power-on) has ended;
        ``/health`` says ``starting`` until it has (``cell serve``: the API answers at once)."""
        for job_id in self.jobs.recovered:
            log.warning("job %s was interrupted by the previous run; marked interrupted", job_id)
        self.host_watch.start()
        if not connect_in_background:
            self.links.connect_all()
        self.gripper_ops.start(connect_in_background)
        self.links.start(first_tries=connect_in_background)
        self.storage.start()
        self.snapshot.start()
        self.alarms.start()
        self.check_schedule.start()
        self.retention.start()

    def close(self) -> None:
        """Stop the arm first, then everything else."""
        try:
            self.stop("service", reason="shutdown")
        except Exception:
            log.exception("stop at shutdown failed")
        self.check_schedule.close()
        self.retention.close()
        self.alarms.close()
        self.links.close()
        self.core.runner.join(timeout_s=5.0)
        self.snapshot.close()
        self.storage.close()
        self.gripper_ops.close()
        self.stopper.close()
        self.hw.close()
        self.jobs.close()
        self.host_watch.close()

    # -- reads ----------------------------------------------------------------------------
    def arm_state(self) -> ArmState:
        try:
            return self.core.arm.state()
        except DriverError as err:
            raise driver_error(err, "reading the arm state") from err

    def health(self) -> dict[str, Any]:
        """From the snapshot (cell.supervision.snapshot): never waits on a device."""
        return self.snapshot.health()

    def status(self) -> dict[str, Any]:
        """From the snapshot (cell.supervision.snapshot): never waits on a device."""
        return self.snapshot.status()

    def job(self, job_id: str) -> Job:
        job = self.jobs.get(job_id)
        if job is None:
            raise NotFoundError(ErrorCode.job_not_found, f"no job with id {job_id!r}")
        return job

    def latest_frame(self) -> Frame:
        return self.core.locator.latest_frame()

    @property
    def last_locate(self) -> Located | None:
        return self.core.locator.last

    def preview(self, estimate: bool) -> tuple[Frame, PoseResult | None, str | None]:
        return self.core.locator.preview(estimate)

    def commanded(self) -> list[Any]:
        """What the guard let through to the arm, oldest first (for audits and tests)."""
        return self.core.arm.commanded()

    # -- commands -----------------------------------------------------------------------------
    def locate(self, caller: str, n_frames: int = 1) -> Located:
        with self.core.audit.command(caller, "locate", {"n_frames": n_frames}) as note:
            loc = approach_mod.locate(self.core, n_frames)
            note.detail = f"rms {loc.result.rms_px:.3f} px"
            return loc

    def locate_all(self, caller: str, recipe: str | int | None = None) -> LocatedParts:
        """Every part in view: of the layout in use, or of every target of ``recipe``
        (name or number; its targets' names name the layouts)."""
        layouts = None
        if recipe is not None:
            layouts = {t.name: t.model() for t in self.recipes.get(recipe).targets}
        with self.core.audit.command(caller, "locate", {"all": True, "recipe": recipe}) as note:
            parts = self.core.locator.locate_all(layouts)
            note.detail = f"{len(parts.instances)} part(s)"
            self.core.events.publish("parts", {"parts": [
                {"id": p.id, "layout": p.layout, "T_base_target": p.T_base_target.json_dict()}
                for p in parts.instances]})
            return parts

    def approach(self, caller: str, *, standoff_mm: float | None = None,
                 speed_mm_s: float | None = None, T_target_tcp: Matrix4 | None = None,
                 use_last_locate: bool = False, wait: bool = False,
                 wait_timeout_s: float = 120.0,
                 mode: ApproachMode | None = None,
                 recipe: dict[str, Any] | None = None, view: Features | None = None,
                 layout: Target | None = None) -> Job:
        """Approach job; ``mode`` None: ``[approach] mode`` (see cell.actions.approach); ``recipe``:
        the recipe record the job keeps; ``view``: the taught view (mode ``ibvs``); ``layout``:
        the dot layout looked for during this job only (a recipe's target)."""
        self._drift_gate(caller, "approach")
        return approach_mod.start_approach(
            self.core, caller, standoff_mm=standoff_mm, speed_mm_s=speed_mm_s,
            T_target_tcp=T_target_tcp, use_last_locate=use_last_locate, wait=wait,
            wait_timeout_s=wait_timeout_s, mode=mode, recipe=recipe, view=view, layout=layout)

    def track(self, caller: str, *, standoff_mm: float, T_target_tcp: Matrix4 | None = None,
              duration_s: float, wait: bool = False, wait_timeout_s: float = 120.0,
              mode: ApproachMode = ApproachMode.servo, view: Features | None = None,
              recipe: dict[str, Any] | None = None, layout: Target | None = None) -> Job:
        """Track job: hold the TCP at the standoff pose on a moving target (cell.actions.track),
        or the taught view (mode ``ibvs``); look-and-move cannot follow a moving target;
        ``recipe``: the recipe record the job keeps; ``layout``: the dot layout looked for
        during this job only."""
        self._drift_gate(caller, "track")
        if mode == ApproachMode.ibvs:
            return track.start_ibvs_track(self.core, caller, standoff_mm=standoff_mm,
                                          duration_s=duration_s, T_target_tcp=T_target_tcp,
                                          view=view, wait=wait, wait_timeout_s=wait_timeout_s)
        if mode != ApproachMode.servo:
            raise LimitError(ErrorCode.invalid_request,
                             f"track mode must be 'servo' or 'ibvs', got '{mode}'")
        return track.start_track(self.core, caller, standoff_mm=standoff_mm,
                                 duration_s=duration_s, T_target_tcp=T_target_tcp, wait=wait,
                                 wait_timeout_s=wait_timeout_s, recipe=recipe, layout=layout)

    def pick(self, caller: str, *, recipe: str | int | None = None, target: str = "",
             place: str | None = None, standoff_mm: float | None = None,
             mode: ApproachMode | None = None, retract: str | None = None, wait: bool = False,
             wait_timeout_s: float = 180.0) -> Job:
        """Pick job (cell.actions.pick): the next part of the recipe's target (None: the
        cell's ``[target]`` with ``[approach]`` and ``[pick]``'s values), placed at the
        base-frame pose taught as ``place`` (None: kept in the gripper after the retract). A
        refusal (unknown recipe or pose, a pose the arm cannot reach) moves nothing."""
        params = {"recipe": recipe, "target": target, "place": place, "standoff_mm": standoff_mm,
                  "mode": mode, "retract": retract}
        try:
            self._drift_gate(caller, "pick", audited=False)
            record, layout, plan = self._pick_plan(recipe, target, place, standoff_mm, mode,
                                                   retract)
        except CellError:
            with self.core.audit.command(caller, "pick", params):
                raise
        # the recipe's other targets may share the view: the pick tells their parts apart
        beside = None if recipe is None else {
            t.name: t.model() for t in self.recipes.get(recipe).targets}
        return pick_mod.start_pick(self.core, self.gripper_ops if self.hw.gripper else None,
                                   caller, plan, recipe=record, layout=layout,
                                   layout_name=IN_USE if record is None
                                   else record["target"], beside=beside, wait=wait,
                                   wait_timeout_s=wait_timeout_s)

    def _pick_plan(self, recipe: str | int | None, target: str, place: str | None,
                   standoff_mm: float | None, mode: ApproachMode | None,
                   retract: str | None = None
                   ) -> tuple[dict[str, Any] | None, Target | None, pick_mod.PickPlan]:
        placed = None if place is None else (place, self.taught.get(place).place_pose())
        if recipe is None:
            T_target_tcp, _ = self.taught.for_job(None, mode)
            retract_to = None if retract is None else (
                retract, self.taught.get(retract).place_pose())
            return None, None, pick_mod.resolve_plan(
                self.core, standoff_mm=standoff_mm, speed_mm_s=None, T_target_tcp=T_target_tcp,
                mode=mode, place=placed, retract_to=retract_to)
        found = self.recipes.get(recipe)
        chosen = found.target(target)
        retract = retract or chosen.retract_taught or None
        retract_to = None if retract is None else (retract,
                                                   self.taught.get(retract).place_pose())
        T_target_tcp, _ = self.taught.for_job(chosen.taught or None, chosen.mode)
        return found.record(chosen), chosen.model(), pick_mod.resolve_plan(
            self.core, standoff_mm=chosen.standoff_mm if standoff_mm is None else standoff_mm,
            speed_mm_s=chosen.speed_mm_s, T_target_tcp=T_target_tcp,
            mode=chosen.mode if mode is None else mode, place=placed,
            grasp_speed_mm_s=chosen.grasp_speed_mm_s, retract_mm=chosen.retract_mm,
            grip_window_mm=(chosen.grip_min_mm, chosen.grip_max_mm), retract_to=retract_to)

    def _drift_gate(self, caller: str, command: str, audited: bool = True) -> None:
        """With ``[check] on_drift = "refuse"``, a job that relies on the calibration is
        refused while a ``calibration_drift`` alarm is unacknowledged (a check that just
        ended counts at once); nothing moves."""
        if self.config.check.on_drift != "refuse":
            return
        self.alarms.check_drift()
        alarm = self.alarms.active_drift()
        if alarm is None:
            return
        err = RefusedError(ErrorCode.calibration_drift,
                           f"the calibration drifted (alarm {alarm.id}: {alarm.message}); "
                           f"{command} is refused until the alarm is acknowledged or a "
                           "calibration is applied ([check] on_drift = \"refuse\")")
        if not audited:
            raise err
        with self.core.audit.command(caller, command, {"refused_by": "calibration_drift"}):
            raise err

    def record_reference(self, caller: str, wait: bool = False) -> Job:
        """Record the calibration reference around the arm's pose (cell.calibration.check)."""
        return self.checks.record(caller, wait=wait)

    def check_calibration(self, caller: str, wait: bool = False) -> Job:
        """Check the calibration against the reference (cell.calibration.check)."""
        return self.checks.check(caller, wait=wait)

    def jog_step(self, caller: str, *, frame: JogFrame, translation_mm: Any,
                 rotation_deg: Any, speed_mm_s: float | None = None) -> Matrix4:
        return self.jogger.step(caller, frame=frame, translation_mm=translation_mm,
                                rotation_deg=rotation_deg, speed_mm_s=speed_mm_s)

    def jog_start(self, caller: str, *, frame: JogFrame, linear_mm_s: Any,
                  angular_deg_s: Any) -> dict[str, Any]:
        return self.jogger.start(caller, frame=frame, linear_mm_s=linear_mm_s,
                                 angular_deg_s=angular_deg_s)

    def heartbeat(self, caller: str) -> dict[str, Any]:
        return self.jogger.heartbeat(caller)

    def home(self, caller: str, *, speed_deg_s: float | None = None, wait: bool = False,
             wait_timeout_s: float = 120.0) -> Job:
        return recovery.start_home(self.core, caller, speed_deg_s=speed_deg_s, wait=wait,
                                   wait_timeout_s=wait_timeout_s)

    def unlock(self, caller: str) -> dict[str, Any]:
        return recovery.unlock(self.core, caller)

    def power(self, caller: str, on: bool) -> dict[str, Any]:
        return recovery.power(self.core, caller, on)

    def gripper(self, caller: str, action: str, position_mm: float | None = None,
                speed_pct: float = 100.0, force_pct: float = 50.0,
                wait: bool = True) -> dict[str, Any]:
        return self.gripper_ops.command(caller, action, position_mm, speed_pct, force_pct, wait)

    def teach(self, caller: str, name: str, samples: int = 5,
              max_spread_mm: float = DEFAULT_MAX_SPREAD_MM,
              max_spread_deg: float = DEFAULT_MAX_SPREAD_DEG,
              replace: bool = True, frame: TaughtFrame = "target") -> TaughtPose:
        """Teach ``name`` at the arm's resting pose into :attr:`taught`, relative to the target
        or in the base frame (cell.features.teach); nothing moves."""
        return teach(self, self.taught, caller, name, samples, max_spread_mm, max_spread_deg,
                     replace, frame)

    def camera_settings(self) -> dict[str, Any]:
        return camera_settings(self.core)

    def apply_camera_settings(self, caller: str, *, exposure_us: int | None = None,
                              iso: int | None = None,
                              focus: FocusSetting | None = None) -> dict[str, Any]:
        return apply_camera_settings(self.core, caller, exposure_us=exposure_us, iso=iso,
                                     focus=focus)

    def stop(self, caller: str, reason: str = "requested") -> dict[str, Any]:
        """Always accepted, through the one stop path (cell.actions.stop): the motion slot's holder
        is cancelled (a flag: no new command can pass the guard from then on), the stop
        thread tells the arm to stop, then the job is cancelled and the stop audited."""
        return self.stopper.stop(caller, reason)

    # -- configuration changes ------------------------------------------------------------------
    def set_hand_eye(self, T_camera: Matrix4) -> None:
        """Use a new camera mount from now on (after a calibration is applied):
        ``T_flange_camera`` for a camera on the flange, ``T_base_camera`` for a fixed one.

        The last locate is forgotten: it was mapped into the base frame with the old mount.
        """
        position_mm, rotvec_rad = pose_from_T(T_camera)
        pose = PoseConfig(position_mm=(position_mm[0], position_mm[1], position_mm[2]),
                          rotvec_rad=(rotvec_rad[0], rotvec_rad[1], rotvec_rad[2]))
        with self.core.lock:
            T = np.asarray(T_camera, dtype=float)
            T_flange_tcp = self.core.frames.T_flange_tcp
            if self.config.fixed_camera:
                frames = CellFrames.fixed(T, T_flange_tcp)
                hand_eye = HandEyeConfig(T_base_camera=pose)
            else:
                frames = CellFrames(T, T_flange_tcp)
                hand_eye = HandEyeConfig(T_flange_camera=pose)
            self.core.frames = frames
            self.config = self.config.model_copy(update={"hand_eye": hand_eye})
            self.core.config = self.config
            self.core.locator.set_frames(frames)
        while (alarm := self.alarms.active_drift()) is not None:
            self.alarms.acknowledge(alarm.id, "calibration applied")
