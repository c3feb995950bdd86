"""From images and robot poses to a judged hand-eye result (used by the CLI and the routine).

Steps: detect the board in every image (views without it are skipped, not fatal), board pose
per view with the given intrinsics, every AX = XB method, the joint refinement seeded by the
chosen method, a diagnostic refinement with free intrinsics, the hybrid (the AX = XB rotation
held, translation and board refined on every image point), and the verdict.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import replace

import numpy as np
from numpy.typing import NDArray

from cell.calibration.dataset import HandEyeDataset
from cell.calibration.observe import ObservationError, dot_target_observer
from cell.calibration.report import (
    HandEyeReport,
    MethodResult,
    joint_is_trusted,
    judge,
    kinematic_explains,
)
from estimator import CameraModel
from estimator.calib.board import Board, board_pose, detect_board
from estimator.calib.eye_to_hand import eye_to_hand_poses
from estimator.calib.handeye import SOLVERS, HandEyeError, board_spread, refine_joint
from estimator.calib.kinematic import MIN_VIEWS as KINEMATIC_MIN_VIEWS
from estimator.calib.kinematic import KinematicResult, refine_kinematic
from estimator.kinematics import UR_DH, DHTable

Progress = Callable[[str, int, int], None]  # (stage, done, total)

METHODS: tuple[str, ...] = tuple(SOLVERS)
REFINED: tuple[str, ...] = ("joint", "hybrid")  # need the refinement over every image point
AUTO = "auto"
CHOICES: tuple[str, ...] = (*METHODS, *REFINED, AUTO)
# The one default everywhere (CLI re-solve, CLI and API routine): ``auto``, which chooses after
# the refinement. The free joint fit over every image point is the best answer when the robot's
# poses are exact (it then leaves about the images' own noise); when it leaves more, the poses
# are off (an arm on its nominal kinematics: tenths of a millimetre), and those errors turn the
# free fit by tenths of a degree about the optical axis, the images' weak direction
# (docs/calibration.md), so the hybrid is chosen: the motions' rotation (AX = XB, which position
# errors do not touch), the translation and board fitted to every image point. Re-solving a
# routine's saved views chooses the same way, so it gives the routine's answer.
DEFAULT_METHOD = AUTO
ROTATION_FROM = "park"  # the hybrid's rotation: the Procrustes fit of the motions' axes


def _quiet(stage: str, done: int, total: int) -> None:
    _ = (stage, done, total)


def solve_dataset(
    dataset: HandEyeDataset,
    chosen: str = DEFAULT_METHOD,
    refine: bool = True,
    progress: Progress | None = None,
    fixed_camera: bool = False,
) -> HandEyeReport:
    """Find the pattern in every view's image (views without it are skipped), then solve:
    a board's features go to :func:`solve_views`, the dot target's observations (the same the
    guided routine makes) to :func:`solve_observations`. With ``fixed_camera`` the views are
    of a plate held by the tool before a fixed camera: the flange poses are inverted
    (:mod:`estimator.calib.eye_to_hand`) and the report's ``T_flange_camera`` is
    ``T_base_camera``."""
    report = progress or _quiet
    if fixed_camera:
        inverted = eye_to_hand_poses([v.T_base_flange for v in dataset.views])
        dataset = replace(dataset, views=tuple(
            replace(v, T_base_flange=T) for v, T in zip(dataset.views, inverted, strict=True)))
    total = len(dataset.views)
    if dataset.board is None:
        return _solve_target_dataset(dataset, chosen, refine, report, fixed_camera)
    names, flanges, points, skipped, joints = [], [], [], [], []
    all_joints = None if fixed_camera else dataset.joints()
    for k, view in enumerate(dataset.views):
        corners = detect_board(dataset.board, view.load_image())
        if corners is None:
            skipped.append(view.name)
        else:
            names.append(view.name)
            flanges.append(view.T_base_flange)
            points.append(corners)
            if all_joints is not None:
                joints.append(all_joints[k])
        report("detect", k + 1, total)
    return solve_views(dataset.camera, dataset.board, names, flanges, points, chosen, refine,
                       tuple(skipped), report, *_kinematics(dataset, joints))


def _solve_target_dataset(
    dataset: HandEyeDataset, chosen: str, refine: bool, report: Progress,
    fixed_camera: bool,
) -> HandEyeReport:
    assert dataset.target is not None
    observe = dot_target_observer(dataset.target)
    names, flanges, observations, skipped, joints = [], [], [], [], []
    all_joints = None if fixed_camera else dataset.joints()
    for k, view in enumerate(dataset.views):
        try:
            observations.append(observe(view.load_image(), dataset.camera))
        except ObservationError:
            skipped.append(view.name)
        else:
            names.append(view.name)
            flanges.append(view.T_base_flange)
            if all_joints is not None:
                joints.append(all_joints[k])
        report("detect", k + 1, len(dataset.views))
    return solve_observations(
        dataset.camera, names, flanges, [o.object_points_mm for o in observations],
        [o.image_points_px for o in observations], [o.T_camera_board for o in observations],
        [o.rms_px for o in observations], chosen, refine, tuple(skipped), report,
        *_kinematics(dataset, joints),
    )


def _kinematics(dataset: HandEyeDataset, joints: list[NDArray[np.float64]]
                ) -> tuple[list[NDArray[np.float64]] | None, DHTable | None]:
    """The used views' joints and the arm's nominal table, when the dataset has them."""
    if not joints or dataset.arm_model is None:
        return None, None
    return joints, UR_DH[dataset.arm_model]


def solve_views(
    camera: CameraModel,
    board: Board,
    names: Sequence[str],
    T_base_flange: Sequence[NDArray[np.float64]],
    image_points_px: Sequence[NDArray[np.float64]],
    chosen: str = DEFAULT_METHOD,
    refine: bool = True,
    skipped: tuple[str, ...] = (),
    progress: Progress | None = None,
    joints_rad: Sequence[NDArray[np.float64]] | None = None,
    arm_geometry: DHTable | None = None,
) -> HandEyeReport:
    """Solve and judge from detected board features (one (N, 2) array per view)."""
    poses = [board_pose(board, pts, camera) for pts in image_points_px]
    obj = board.object_points_mm()
    return solve_observations(
        camera, names, T_base_flange, [obj] * len(poses), image_points_px,
        [p.T_camera_board for p in poses], [p.rms_px for p in poses], chosen, refine, skipped,
        progress, joints_rad, arm_geometry,
    )


def solve_observations(
    camera: CameraModel,
    names: Sequence[str],
    T_base_flange: Sequence[NDArray[np.float64]],
    object_points_mm: Sequence[NDArray[np.float64]],
    image_points_px: Sequence[NDArray[np.float64]],
    T_camera_board: Sequence[NDArray[np.float64]],
    pnp_rms_px: Sequence[float],
    chosen: str = DEFAULT_METHOD,
    refine: bool = True,
    skipped: tuple[str, ...] = (),
    progress: Progress | None = None,
    joints_rad: Sequence[NDArray[np.float64]] | None = None,
    arm_geometry: DHTable | None = None,
) -> HandEyeReport:
    """Solve and judge from per-view observations of any rigid target (board or dot plate).

    ``T_camera_board`` is each view's own pose of the target and ``pnp_rms_px`` how well that
    pose explains the view's image points. With each view's ``joints_rad`` and the arm's
    nominal ``arm_geometry`` (and enough views), the arm's geometry is fitted with the mount
    too; when that explains the images and the nominal kinematics do not, the default choice
    becomes the ``kinematic`` result.
    """
    if chosen not in CHOICES:
        raise HandEyeError(f"unknown method {chosen!r}; choose one of {', '.join(CHOICES)}")
    if chosen == AUTO and not refine:
        chosen = "tsai"
    if chosen in REFINED and not refine:
        raise HandEyeError(f"--method {chosen} needs the refinement over every image point")
    report = progress or _quiet
    methods: dict[str, MethodResult] = {}
    for k, name in enumerate(METHODS):
        X = SOLVERS[name](T_base_flange, T_camera_board)
        methods[name] = MethodResult(name, X, board_spread(T_base_flange, T_camera_board, X))
        report("solve", k + 1, len(METHODS))
    seed = methods["tsai" if chosen in (*REFINED, AUTO) else chosen]
    joint = joint_spread = free = hybrid = None
    kinematic: KinematicResult | None = None
    pnp = tuple(float(r) for r in pnp_rms_px)
    if refine:
        joint = refine_joint(T_base_flange, image_points_px, object_points_mm, camera,
                             seed.T_flange_camera, seed.spread.T_base_board_mean)
        joint_spread = board_spread(T_base_flange, T_camera_board, joint.T_flange_camera)
        # Diagnostic only: if freeing the intrinsics cuts the rms, they are what is wrong.
        free = refine_joint(T_base_flange, image_points_px, object_points_mm, camera,
                            joint.T_flange_camera, joint.T_base_board, free_intrinsics=True)
        axes = methods[ROTATION_FROM]
        hybrid = refine_joint(T_base_flange, image_points_px, object_points_mm, camera,
                              axes.T_flange_camera, axes.spread.T_base_board_mean,
                              hold_rotation=True)
        report("refine", 1, 1)
        if (joints_rad is not None and arm_geometry is not None
                and len(joints_rad) >= KINEMATIC_MIN_VIEWS):
            kinematic = refine_kinematic(joints_rad, image_points_px, object_points_mm, camera,
                                         arm_geometry, joint.T_flange_camera, joint.T_base_board)
        if chosen == AUTO:
            if joint_is_trusted(joint.rms_px, pnp):
                chosen = "joint"
            elif kinematic is not None and kinematic_explains(joint, kinematic, pnp):
                chosen = "kinematic"
            else:
                chosen = "hybrid"
    depth = float(np.mean([T[2, 3] for T in T_camera_board]))
    verdict = judge(tuple(names), pnp, methods, joint, free, chosen, depth,
                    0.5 * (camera.fx + camera.fy), hybrid, kinematic)
    return HandEyeReport(
        view_names=tuple(names), skipped_views=skipped, pnp_rms_px=pnp, methods=methods,
        joint=joint, joint_spread=joint_spread, joint_free_intrinsics=free, chosen=chosen,
        verdict=verdict, hybrid=hybrid, kinematic=kinematic,
    )
