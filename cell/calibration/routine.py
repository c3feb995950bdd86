"""The guided hand-eye routine: move the arm around a start pose, look, solve, judge.

Works on the :class:`cell.motion.guard.GuardedArm` (never the raw arm) and any
:class:`drivers.camera.Camera`; the cell and the CLI hand it their guarded arm, so every view
pose is checked against the limits first (a refused view is skipped, not moved to) and a stop
ends the routine.

The poses tilt the camera about the target (so it stays in view) about several axes and roll
it about the optical axis, because AX = XB is only determined by rotations about at least two
different axes. The target's position for that pivot comes from the first view and the current
(rough) hand-eye guess; a guess off by centimetres only shifts the target in the image.

With a fixed camera (eye-to-hand) the arm carries the target (clamped to the tool) before the
camera instead: the views turn the tool about the plate's centre, so the plate tilts about
several axes across the camera's line of sight and rolls about it, and shift it across the
image; the flange poses are inverted for the solvers (:mod:`estimator.calib.eye_to_hand`) and
the result is ``T_base_camera``.

Each view is taken from a frame exposed after the arm has stopped and settled, with the flange
pose the arm reports for that frame's timestamp, so a slow camera cannot pair an image with the
wrong pose. Views that fail (unreachable pose, target not found) are reported and skipped.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from numpy.typing import NDArray
from scipy.spatial.transform import Rotation

from cell.calibration.dataset import HandEyeDataset, save_project_dataset
from cell.calibration.defaults import DEFAULT_VIEWS
from cell.calibration.observe import Observation, ObservationError, Observer
from cell.calibration.report import HandEyeReport
from cell.calibration.solve import DEFAULT_METHOD, Progress, solve_observations
from cell.error_codes import ErrorCode
from cell.errors import CellError, LimitError, RefusedError
from cell.motion.guard import GuardedArm
from drivers.camera import Camera, Frame
from drivers.errors import DriverError
from estimator import CameraModel, Target
from estimator.calib.board import Board
from estimator.calib.eye_to_hand import eye_to_hand_poses
from estimator.calib.handeye import HandEyeError
from estimator.kinematics import DHTable
from estimator.transforms import invert_T, make_T

Matrix4 = NDArray[np.float64]

GOLDEN_ANGLE_RAD = np.pi * (3.0 - np.sqrt(5.0))


class RoutineError(CellError):
    """The routine cannot go on (no target at the start pose, too few good views)."""

    kind = "conflict"


@dataclass(frozen=True)
class RoutineSettings:
    n_views: int = DEFAULT_VIEWS  # including the start pose
    # camera tilt about the target (alternating with 0.6 of it) and largest roll about the
    # optical axis: 30 / 60 deg rather than 18 / 35 bring the AX = XB rotation error from
    # 0.016-0.055 deg to 0.012-0.020 deg on the simulated cell (docs/calibration.md)
    tilt_deg: float = 30.0
    roll_deg: float = 60.0
    speed_mm_s: float = 200.0
    accel_mm_s2: float = 800.0
    settle_s: float = 0.15  # after the arm stops, before a frame counts
    frame_timeout_s: float = 2.0
    min_views: int = 6
    chosen: str = DEFAULT_METHOD  # auto: joint, or hybrid when the arm's poses are off
    return_to_start: bool = True
    shift_mm: float = 60.0  # fixed camera only: largest move of the plate across the image

    def __post_init__(self) -> None:
        if self.n_views < 3 or self.min_views < 3:
            raise ValueError("a hand-eye routine needs at least 3 views")
        if not 0 < self.tilt_deg <= 45 or not 0 <= self.roll_deg <= 90:
            raise ValueError("tilt_deg must be in (0, 45] and roll_deg in [0, 90]")
        if self.speed_mm_s <= 0 or self.accel_mm_s2 <= 0:
            raise ValueError("speed and acceleration must be positive")


@dataclass(frozen=True)
class RoutineResult:
    report: HandEyeReport
    T_base_flange: tuple[Matrix4, ...]  # of the views used
    observations: tuple[Observation, ...]
    failed: tuple[tuple[int, str], ...] = field(default_factory=tuple)  # (view, reason)
    images: tuple[NDArray[np.uint8], ...] = ()  # of the views used, as the camera gave them
    camera: CameraModel | None = None  # the intrinsics the views were solved with
    joints_rad: tuple[NDArray[np.float64], ...] = ()  # of the views used, as the arm gave them


def save_views(folder: str | Path, result: RoutineResult, pattern: Board | Target,
               arm_model: str | None = None) -> HandEyeDataset:
    """Write the routine's views (PNG, lossless), flange poses and joints (with ``arm_model``,
    the arm they go with) as a project dataset, so ``cell calibrate hand-eye FOLDER``
    re-solves exactly what the routine solved (same images, same observations, same answer)
    and the calibration can be audited or redone later."""
    if result.camera is None or len(result.images) != len(result.T_base_flange):
        raise ValueError("this routine result holds no images to save")
    names = [f"view-{k:02d}.png" for k in range(len(result.images))]
    return save_project_dataset(folder, result.camera, pattern,
                                list(zip(names, result.T_base_flange, strict=True)),
                                result.images, result.joints_rad or None, arm_model)


def plan_poses(
    T_base_flange_start: Matrix4,
    T_flange_camera_guess: Matrix4,
    pivot_camera_mm: NDArray[np.float64],
    settings: RoutineSettings,
) -> list[Matrix4]:
    """Flange poses that turn the camera about the target point, starting with the start pose.

    Tilt axes lie in the image plane at golden-angle steps, so any few views already rotate
    about different axes; the roll about the optical axis alternates in sign and size.
    """
    T_base_camera0 = T_base_flange_start @ T_flange_camera_guess
    pivot = T_base_camera0[:3, :3] @ pivot_camera_mm + T_base_camera0[:3, 3]
    X_inv = invert_T(T_flange_camera_guess)
    poses = [np.asarray(T_base_flange_start, dtype=float)]
    for k in range(1, settings.n_views):
        azimuth = k * GOLDEN_ANGLE_RAD
        tilt = np.radians(settings.tilt_deg) * (1.0 if k % 2 else 0.6)
        roll = np.radians(settings.roll_deg) * np.sin(1.7 * k)
        axis = np.array([np.cos(azimuth), np.sin(azimuth), 0.0])
        R_cam = (Rotation.from_rotvec(axis * tilt) * Rotation.from_rotvec([0, 0, roll]))
        R_base = T_base_camera0[:3, :3] @ R_cam.as_matrix() @ T_base_camera0[:3, :3].T
        turn = make_T(R_base, pivot - R_base @ pivot)  # rotation about the pivot point
        poses.append(turn @ T_base_camera0 @ X_inv)
    return poses


def plan_fixed_poses(
    T_base_flange_start: Matrix4,
    T_base_camera_guess: Matrix4,
    pivot_base_mm: NDArray[np.float64],
    settings: RoutineSettings,
) -> list[Matrix4]:
    """Flange poses that turn a tool-held plate before a fixed camera, starting with the start
    pose.

    The tool turns about the plate's centre (``pivot_base_mm``), so the plate stays in view:
    tilt axes across the camera's line of sight at golden-angle steps, a roll about that line
    alternating in sign and size, as for a camera on the hand. Each view also shifts the plate
    across the image by up to ``shift_mm`` (another angle sequence), so the views do not all
    share one ray of the camera.
    """
    R_c = np.asarray(T_base_camera_guess, dtype=float)[:3, :3]
    pivot = np.asarray(pivot_base_mm, dtype=float)
    start = np.asarray(T_base_flange_start, dtype=float)
    poses = [start]
    for k in range(1, settings.n_views):
        azimuth = k * GOLDEN_ANGLE_RAD
        tilt = np.radians(settings.tilt_deg) * (1.0 if k % 2 else 0.6)
        roll = np.radians(settings.roll_deg) * np.sin(1.7 * k)
        axis = np.array([np.cos(azimuth), np.sin(azimuth), 0.0])
        R_cam = Rotation.from_rotvec(axis * tilt) * Rotation.from_rotvec([0, 0, roll])
        R_base = R_c @ R_cam.as_matrix() @ R_c.T
        step = 2.4 * k + 1.0
        shift_cam = settings.shift_mm * np.array([np.cos(step), np.sin(step), 0.0]) \
            * (0.5 + 0.5 * ((k * 0.618) % 1.0))
        turn = make_T(R_base, pivot - R_base @ pivot + R_c @ shift_cam)
        poses.append(turn @ start)
    return poses


def shortest_tour(poses: list[Matrix4], rotation_mm_per_rad: float = 1000.0) -> list[Matrix4]:
    """The same poses, the first kept first, the rest visited nearest-first.

    A UR's linear move runs its tool speed as rad/s when it mostly turns, so the routine's
    time is its total rotation: the plans alternate roll and tilt for the solver's sake, and
    taken in their planned order they turn about twice as far as needed (12 views: ~500 deg
    against ~250). The solvers do not depend on the order of the views. ``rotation_mm_per_rad``
    weighs a turn against a shift, as the tool speed does."""
    left = list(range(1, len(poses)))
    order = [0]
    while left:
        last = poses[order[-1]]

        def cost(j: int, last: Matrix4 = last) -> float:
            turn = Rotation.from_matrix(last[:3, :3].T @ poses[j][:3, :3]).magnitude()
            shift = float(np.linalg.norm(poses[j][:3, 3] - last[:3, 3]))
            return max(turn * rotation_mm_per_rad, shift)

        nearest = min(left, key=cost)
        order.append(nearest)
        left.remove(nearest)
    return [poses[k] for k in order]


def run_hand_eye_routine(
    arm: GuardedArm,
    camera: Camera,
    observer: Observer,
    T_flange_tcp: Matrix4,
    T_flange_camera_guess: Matrix4,
    settings: RoutineSettings | None = None,
    progress: Progress | None = None,
    fixed_camera: bool = False,
    intrinsics: Callable[[CameraModel], CameraModel] | None = None,
    arm_geometry: DHTable | None = None,
) -> RoutineResult:
    """Collect views around the arm's current pose and solve; the arm ends where it started.

    ``T_flange_tcp`` must be the TCP the arm is configured with (poses are commanded as TCP
    poses); ``T_flange_camera_guess`` only aims the views. With ``fixed_camera`` the target is
    on the tool, the guess is ``T_base_camera`` and so is the report's result (its
    ``T_flange_camera`` field); ``T_base_flange`` stays the flange poses as the arm gave them.
    ``intrinsics`` maps the intrinsics a frame reports to the ones to solve with (the cell's
    :class:`cell.vision.intrinsics.IntrinsicsPolicy`; None: the frame's own).
    ``arm_geometry``: the arm's nominal DH table; with it and enough views (a camera on the
    hand), the arm's geometry is fitted with the mount (:mod:`estimator.calib.kinematic`).
    Raises RoutineError when the target
    is not visible at the start or fewer than ``min_views`` views succeed, and lets
    ``drivers.errors`` through when the arm faults (protective stop, connection lost).
    """
    s = settings or RoutineSettings()
    report = progress or (lambda stage, done, total: None)
    tcp_inv = invert_T(T_flange_tcp)
    T_start_tcp = arm.tcp_pose()
    model_for = intrinsics or (lambda device: device)
    flange0, obs0, intrinsics_used, image0 = _capture(arm, camera, observer, tcp_inv, s,
                                                      model_for)
    joints = [arm.joint_positions_rad()]
    if isinstance(obs0, str):
        raise RoutineError(ErrorCode.target_not_visible, f"at the start pose: {obs0}")
    centre = obs0.object_points_mm.mean(axis=0)
    pivot = obs0.T_camera_board[:3, :3] @ centre + obs0.T_camera_board[:3, 3]
    if fixed_camera:
        G = np.asarray(T_flange_camera_guess, dtype=float)
        plan = plan_fixed_poses(flange0, G, G[:3, :3] @ pivot + G[:3, 3], s)
    else:
        plan = plan_poses(flange0, T_flange_camera_guess, pivot, s)
    plan = shortest_tour(plan)
    flanges, observations, images, failed = [flange0], [obs0], [image0], []
    report("views", 1, len(plan))
    try:
        for k, T_base_flange in enumerate(plan[1:], start=1):
            try:
                arm.move_linear(T_base_flange @ T_flange_tcp, s.speed_mm_s, s.accel_mm_s2)
            except (DriverError, LimitError, RefusedError) as err:
                # the guard's no, or the controller's (an unreachable view comes through the
                # guard as refused, motion_failed); anything else, or a fault, ends the routine
                if not arm.state().ready or (isinstance(err, RefusedError)
                                             and err.code != ErrorCode.motion_failed):
                    raise
                failed.append((k, f"move refused: {err}"))
                report("views", k + 1, len(plan))
                continue
            flange, obs, _, image = _capture(arm, camera, observer, tcp_inv, s, model_for)
            if isinstance(obs, str):
                failed.append((k, obs))
            else:
                flanges.append(flange)
                observations.append(obs)
                images.append(image)
                joints.append(arm.joint_positions_rad())  # the arm stands: the view's joints
            report("views", k + 1, len(plan))
    finally:
        if s.return_to_start and arm.state().ready:
            arm.move_linear(T_start_tcp, s.speed_mm_s, s.accel_mm_s2)
    if len(observations) < s.min_views:
        reasons = "; ".join(f"view {k}: {r}" for k, r in failed)
        raise RoutineError(
            ErrorCode.too_few_views,
            f"only {len(observations)} of {len(plan)} views succeeded (need {s.min_views}): "
            f"{reasons}",
        )
    try:
        result = solve_observations(
            intrinsics_used,
            [f"view-{k:02d}" for k in range(len(observations))],
            eye_to_hand_poses(flanges) if fixed_camera else flanges,
            [o.object_points_mm for o in observations], [o.image_points_px for o in observations],
            [o.T_camera_board for o in observations], [o.rms_px for o in observations],
            chosen=s.chosen, progress=report,
            joints_rad=None if fixed_camera or arm_geometry is None else joints,
            arm_geometry=arm_geometry,
        )
    except HandEyeError as err:
        raise RoutineError(ErrorCode(err.code), str(err)) from err
    return RoutineResult(result, tuple(flanges), tuple(observations), tuple(failed),
                         tuple(images), intrinsics_used, tuple(joints))


def _capture(
    arm: GuardedArm, camera: Camera, observer: Observer, tcp_inv: Matrix4, s: RoutineSettings,
    model_for: Callable[[CameraModel], CameraModel],
) -> tuple[Matrix4, Observation | str, CameraModel, NDArray[np.uint8]]:
    """A frame exposed after the arm settled: its flange pose, what it shows, the intrinsics
    it was observed with and the image."""
    stopped = time.monotonic()
    time.sleep(s.settle_s)
    frame = _frame_after(camera, stopped + s.settle_s, s.frame_timeout_s)
    try:
        T_base_tcp = arm.pose_at(frame.timestamp_s)
    except LookupError:
        T_base_tcp = arm.tcp_pose()
    flange = T_base_tcp @ tcp_inv
    model = model_for(frame.camera)
    try:
        return flange, observer(frame.image, model), model, frame.image.copy()
    except ObservationError as err:
        return flange, str(err), model, frame.image.copy()


def _frame_after(camera: Camera, t_s: float, timeout_s: float) -> Frame:
    deadline = time.monotonic() + timeout_s
    while True:
        frame = camera.latest_frame(timeout_s=max(0.05, deadline - time.monotonic()))
        if frame.timestamp_s >= t_s:
            return frame
        if time.monotonic() > deadline:
            raise RoutineError(ErrorCode.camera_stale,
                               f"no frame exposed after the arm stopped within "
                               f"{timeout_s} s")
