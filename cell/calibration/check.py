"""The calibration check: a fixed reference plate, recorded once, seen again on demand.

Right after a calibration, ``record`` looks at a dot plate fixed in the cell (the target in
use) from the arm's current pose and a few poses tilted about the plate, and keeps each
view's joints and the plate's base-frame pose seen from it. ``check`` drives back to the same
joints and looks again. The same joints put the flange where they put it before, whatever
the arm's kinematic error, so the plate's apparent shift from view to view is what changed
between the flange and the image: the camera's mount, the lens, the plate. A quality engineer
reads it at the tool: the shift applied to the approach goal on the plate (``tcp_error``).

Both are jobs (they move the arm: the motion slot, the guard, a stop cancels them); the
check's results stay in the job history, the calibration's record of how it held. The
reference is one JSON file beside the job database, replaced atomically.
"""

from __future__ import annotations

import json
import logging
import threading
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from cell.calibration.camera_change import camera_change
from cell.calibration.routine import RoutineSettings, plan_poses
from cell.core import CellCore
from cell.error_codes import ErrorCode
from cell.errors import CellError, RefusedError, UnavailableError
from cell.files import replace_text
from cell.jobs.store import Job
from cell.motion.guard import Motion
from cell.results.check import (
    CheckCause,
    CheckedView,
    CheckResult,
    CheckVerdict,
    ReferenceResult,
    ReferenceView,
)
from cell.results.pose import Pose
from cell.vision.frames import approach_tcp, mean_pose
from estimator.transforms import T_from_pose_dict, invert_T, pose_dict, pose_distance

log = logging.getLogger(__name__)
Matrix4 = NDArray[np.float64]

STORE_NAME = "calibration_reference.json"
FORMAT_VERSION = 1
RECORD_KIND = "calibration_reference"
CHECK_KIND = "calibration_check"
SETTLE_S = 0.15  # after the arm stops, before a frame counts
JOINT_SPEED_RAD_S = 0.8
JOINT_ACCEL_RAD_S2 = 1.5
REFERENCE_MARGIN = 3.0  # the plate model must miss this many times less than the camera's
VIEW_NOISE_MM = 0.15  # a check's views disagree by this much with nothing changed (measured)


class ReferenceStoreError(CellError):
    kind = "unavailable"


@dataclass(frozen=True)
class Reference:
    """The recorded reference: each view's joints and the plate seen from there."""

    joints_rad: tuple[tuple[float, ...], ...]
    T_base_reference: tuple[Matrix4, ...]  # per view
    recorded_at: float
    recorded_by: str
    job_id: str

    def as_dict(self) -> dict[str, Any]:
        return {"version": FORMAT_VERSION, "recorded_at": self.recorded_at,
                "recorded_by": self.recorded_by, "job_id": self.job_id,
                "views": [{"joints_rad": list(q), "T_base_reference": pose_dict(T)}
                          for q, T in zip(self.joints_rad, self.T_base_reference, strict=True)]}

    @staticmethod
    def from_dict(d: dict[str, Any]) -> Reference:
        views = d["views"]
        return Reference(tuple(tuple(float(v) for v in w["joints_rad"]) for w in views),
                         tuple(T_from_pose_dict(w["T_base_reference"]) for w in views),
                         float(d["recorded_at"]), str(d["recorded_by"]), str(d["job_id"]))


class ReferenceStore:
    """The one reference of a cell (``path`` None: in memory only)."""

    def __init__(self, path: Path | None) -> None:
        self.path = path
        self._lock = threading.Lock()
        self._reference: Reference | None = None
        if path is not None and path.exists():
            try:
                self._reference = Reference.from_dict(json.loads(path.read_text()))
            except (OSError, ValueError, KeyError, TypeError) as err:
                log.warning("the calibration reference %s is unreadable (%s); record it again",
                            path, err)

    @staticmethod
    def beside_job_db(job_db: str) -> ReferenceStore:
        return ReferenceStore(None if job_db == ":memory:" else Path(job_db).parent / STORE_NAME)

    def get(self) -> Reference | None:
        with self._lock:
            return self._reference

    def put(self, reference: Reference) -> None:
        with self._lock:
            if self.path is not None:
                try:
                    replace_text(self.path, json.dumps(reference.as_dict(), indent=2) + "\n")
                except OSError as err:
                    raise ReferenceStoreError(
                        ErrorCode.dataset_unwritable,
                        f"cannot write the calibration reference {self.path}: {err}") from err
            self._reference = reference


def _miss(predicted: list[Matrix4], seen: list[Matrix4]) -> tuple[float, float]:
    d = [pose_distance(p, s) for p, s in zip(predicted, seen, strict=True)]
    return max(x[0] for x in d), max(x[1] for x in d)


@dataclass(frozen=True)
class Seen:
    joints_rad: NDArray[np.float64]
    T_base_tcp: Matrix4
    T_base_reference: Matrix4
    rms_px: float


class CalibrationCheck:
    """Records the reference and checks against it, as jobs of the cell (``core``)."""

    def __init__(self, core: CellCore, store: ReferenceStore) -> None:
        self.core = core
        self.store = store

    # -- recording ---------------------------------------------------------------------------
    def record(self, caller: str, wait: bool = False, wait_timeout_s: float = 120.0) -> Job:
        """Record the reference around the arm's current pose (the plate in view)."""
        core, cc = self.core, self.core.config.check
        params = {"views": cc.views, "tilt_deg": cc.tilt_deg}

        def check(motion: Motion) -> None:
            self._ready()

        def work(job_id: str, motion: Motion) -> ReferenceResult:
            return self._record(caller, job_id, motion)

        return core.runner.start(RECORD_KIND, caller, params, work, check=check,
                                 needs_camera=True, wait=wait, wait_timeout_s=wait_timeout_s,
                                 motion_name="calibration")

    def _record(self, caller: str, job_id: str, motion: Motion) -> ReferenceResult:
        core, cc = self.core, self.core.config.check
        start = self._look()
        T_flange_tcp = core.frames.T_flange_tcp
        T_base_flange = start.T_base_tcp @ invert_T(T_flange_tcp)
        T_flange_camera = core.frames.T_camera_mount
        T_camera_ref = invert_T(T_base_flange @ T_flange_camera) @ start.T_base_reference
        centre = core.locator.target.points_mm.mean(axis=0)
        pivot = T_camera_ref[:3, :3] @ centre + T_camera_ref[:3, 3]
        settings = RoutineSettings(n_views=cc.views, tilt_deg=cc.tilt_deg, roll_deg=0.0,
                                   speed_mm_s=cc.speed_mm_s)
        seen, failed = [start], []
        for k, T_flange in enumerate(plan_poses(T_base_flange, T_flange_camera, pivot,
                                                settings)[1:], start=1):
            core.runner.progress(job_id, {"stage": "views", "done": k, "total": cc.views})
            try:
                core.arm.move_linear(T_flange @ T_flange_tcp, cc.speed_mm_s,
                                     core.config.approach.accel_mm_s2, what=f"reference view {k}")
                seen.append(self._look())
            except CellError as err:
                motion.raise_if_cancelled(f"at reference view {k}")
                failed.append(f"view {k}: {err.message}")
        motion.raise_if_cancelled("before returning to the start pose")
        core.arm.move_joint(start.joints_rad, JOINT_SPEED_RAD_S, JOINT_ACCEL_RAD_S2,
                            what="back to the reference's first view")
        if len(seen) < 2:
            raise RefusedError(ErrorCode.too_few_views, "the reference needs at least two "
                               f"views of the plate; {'; '.join(failed)}")
        self.store.put(Reference(tuple(tuple(float(v) for v in s.joints_rad) for s in seen),
                                 tuple(s.T_base_reference for s in seen), time.time(), caller,
                                 job_id))
        Ts = [s.T_base_reference for s in seen]
        T_mean = mean_pose(Ts)
        return ReferenceResult(
            views=[ReferenceView(view=k, joints_deg=[float(v) for v in np.degrees(s.joints_rad)],
                                 T_base_tcp=Pose.from_T(s.T_base_tcp),
                                 T_base_reference=Pose.from_T(s.T_base_reference),
                                 rms_px=s.rms_px) for k, s in enumerate(seen)],
            T_base_reference=Pose.from_T(T_mean),
            spread_mm=max(pose_distance(T, T_mean)[0] for T in Ts),
            spread_deg=max(pose_distance(T, T_mean)[1] for T in Ts), failed_views=failed)

    # -- checking ----------------------------------------------------------------------------
    def check(self, caller: str, wait: bool = False, wait_timeout_s: float = 120.0) -> Job:
        """Check the calibration against the recorded reference (refused without one)."""
        core = self.core

        def check(motion: Motion) -> None:
            if self.store.get() is None:
                raise RefusedError(ErrorCode.no_reference,
                                   "no calibration reference is recorded: record one (POST "
                                   "/calibration/reference) right after a calibration")
            self._ready()

        def work(job_id: str, motion: Motion) -> CheckResult:
            reference = self.store.get()
            assert reference is not None
            return self._check(job_id, motion, reference)

        return core.runner.start(CHECK_KIND, caller, {}, work, check=check, needs_camera=True,
                                 wait=wait, wait_timeout_s=wait_timeout_s,
                                 motion_name="calibration")

    def _check(self, job_id: str, motion: Motion, reference: Reference) -> CheckResult:
        core, cc = self.core, self.core.config.check
        t0 = time.monotonic()
        start_joints = np.asarray(core.arm.state().joints_rad, dtype=float)
        views: list[CheckedView] = []
        deltas: list[Matrix4] = []
        T_cameras: list[Matrix4] = []  # where the camera was for each view (the same joints)
        T_now: list[Matrix4] = []  # the plate seen from each view now
        n = len(reference.joints_rad)
        for k, (q, T_then) in enumerate(zip(reference.joints_rad, reference.T_base_reference,
                                            strict=True)):
            core.runner.progress(job_id, {"stage": "views", "done": k, "total": n})
            core.arm.move_joint(np.asarray(q), JOINT_SPEED_RAD_S, JOINT_ACCEL_RAD_S2,
                                what=f"reference view {k}")
            now = self._look()
            deltas.append(now.T_base_reference @ invert_T(T_then))  # base frame: then -> now
            T_now.append(now.T_base_reference)
            T_cameras.append(core.frames.T_base_camera(now.T_base_tcp))
            d_mm, d_deg = pose_distance(now.T_base_reference, T_then)
            shift = now.T_base_reference[:3, 3] - T_then[:3, 3]
            views.append(CheckedView(view=k, shift_mm=(float(shift[0]), float(shift[1]),
                                                       float(shift[2])),
                                     distance_mm=d_mm, rotation_deg=d_deg, rms_px=now.rms_px))
        motion.raise_if_cancelled("before returning to the start pose")
        core.arm.move_joint(start_joints, JOINT_SPEED_RAD_S, JOINT_ACCEL_RAD_S2,
                            what="back to the check's start pose")
        T_ref = mean_pose(list(reference.T_base_reference))
        goal = approach_tcp(T_ref, core.config.approach.T_target_tcp.T(),
                            core.config.approach.standoff_mm)
        cause, D_goal, spread = self._explain(list(reference.T_base_reference), T_now,
                                              T_cameras, goal)
        tcp_mm, tcp_deg = pose_distance(D_goal @ goal, goal)
        D = mean_pose(deltas)
        pos_mm, rot_deg = pose_distance(D @ T_ref, T_ref)
        drifted = tcp_mm > cc.tolerance_mm or tcp_deg > cc.tolerance_deg
        verdict: CheckVerdict = "drifted" if drifted else "ok"
        return CheckResult(
            verdict=verdict, cause=cause, tcp_error_mm=tcp_mm, tcp_error_deg=tcp_deg,
            position_error_mm=pos_mm, rotation_error_deg=rot_deg,
            spread_mm=spread[0], spread_deg=spread[1],
            tolerance_mm=cc.tolerance_mm, tolerance_deg=cc.tolerance_deg,
            standoff_mm=core.config.approach.standoff_mm,
            views=views, reference_recorded_at=reference.recorded_at,
            took_s=time.monotonic() - t0)

    def _explain(self, T_then: list[Matrix4], T_now: list[Matrix4], T_cameras: list[Matrix4],
                 goal: Matrix4) -> tuple[CheckCause, Matrix4, tuple[float, float]]:
        """Which change explains the views better, and the base-frame shift it makes in what
        the camera sees from the approach goal on the plate.

        A change in the camera (its mount or lens) changes the plate's pose alike in the
        camera frame of every view (``now = T_c E inv(T_c) then``, one ``E``), and from the
        goal it shifts what the camera sees by that same camera-frame change seen from there
        (closer to the plate than the views: a turned camera moves less there). A plate that
        moved shifts alike in the base frame (``now = D then``, one ``D``), and anything seen
        from anywhere by that. Each model is fitted to the views and judged by how far its
        prediction of each view's plate pose misses (mm at the plate, deg); a fixed camera
        sees from one pose, so its change is the base-frame shift. A camera that moved along
        its own axes shifts the plate almost alike in both frames (the views differ by
        ``tilt_deg``): the plate is blamed only when it explains the views clearly better
        (``REFERENCE_MARGIN``) and the camera model misses by more than the views' own noise
        (``VIEW_NOISE_MM``); otherwise the camera, whose model also gives the right figure
        at the tool for a moved plate seen nearly alike. The camera's change carried to the
        goal keeps a turn only where the views resolve it (:func:`camera_change`). Returns
        the cause, the shift at the goal and the chosen model's largest miss."""
        D = mean_pose([n @ invert_T(t) for t, n in zip(T_then, T_now, strict=True)])
        base_miss = _miss([D @ t for t in T_then], T_now)
        if self.core.frames.is_fixed:
            return "camera", D, base_miss
        changes = [invert_T(c) @ n @ invert_T(t) @ c
                   for t, n, c in zip(T_then, T_now, T_cameras, strict=True)]
        E = mean_pose(changes)
        camera_miss = _miss([c @ E @ invert_T(c) @ t for t, c in zip(T_then, T_cameras,
                                                                     strict=True)], T_now)
        if camera_miss[0] > max(REFERENCE_MARGIN * base_miss[0], VIEW_NOISE_MM):
            return "reference", D, base_miss
        centre = self.core.locator.target.points_mm.mean(axis=0)
        centres = [(invert_T(c) @ t)[:3, :3] @ centre + (invert_T(c) @ t)[:3, 3]
                   for t, c in zip(T_then, T_cameras, strict=True)]
        T_camera_goal = self.core.frames.T_base_camera(goal)
        return "camera", (T_camera_goal @ camera_change(changes, centres)
                          @ invert_T(T_camera_goal)), camera_miss

    # -- shared ------------------------------------------------------------------------------
    def _ready(self) -> None:
        core = self.core
        core.arm.guard.check_speed(core.config.check.speed_mm_s,
                                   core.config.approach.accel_mm_s2)
        core.arm.ready_state()
        if not core.camera.is_connected:
            raise UnavailableError(ErrorCode.camera_lost, "the calibration check needs the camera")

    def _look(self) -> Seen:
        """The plate from where the arm rests, averaged over frames exposed after it
        settled."""
        core = self.core
        core.arm.wait_for_motion()
        after_s = time.monotonic() + SETTLE_S
        time.sleep(SETTLE_S)
        loc = core.locator.locate(core.config.check.frames_per_view, after_s=after_s)
        st = core.arm.state()
        return Seen(np.asarray(st.joints_rad, dtype=float), loc.T_base_tcp, loc.T_base_target,
                    float(max(loc.frame_rms_px)))
