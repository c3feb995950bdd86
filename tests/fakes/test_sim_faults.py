"""Faults at run time in the simulated world: a knocked camera, a shifted lens, a knocked
reference plate and a slipped part, each measured from the pixels and the parts' truth, and each
undone exactly."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from numpy.typing import NDArray

from estimator import CameraModel
from estimator.transforms import T_from_pose, invert_T, translation_T
from fakes.fixed_camera import FixedSimCamera
from fakes.parts import Placement, SimParts
from fakes.sim_camera import SimCamera
from fakes.sim_cell.arm_truth import Matrix4
from fakes.sim_cell.faults import Faults
from fakes.sim_cell.world import SimulatedWorld
from tests.fakes.test_sim_camera import (
    CAM,
    T_BASE_FLANGE0,
    T_BASE_TARGET,
    T_FLANGE_CAMERA,
    TARGET,
    StaticPose,
    dot_centres,
)


@dataclasses.dataclass(frozen=True, eq=False)
class Truth:
    camera: CameraModel
    T_flange_camera: Matrix4

    def with_optics(self, camera: CameraModel, T_mount: Matrix4) -> Truth:
        return Truth(camera, T_mount)


class StillArm:
    def flange_and_tcp(self) -> tuple[Matrix4, Matrix4, float]:
        return T_BASE_FLANGE0, T_BASE_FLANGE0, 0.0

    def protective_stop(self, reason: str) -> None:
        raise AssertionError("not used")


REFERENCE = translation_T(150.0, 0.0, 0.0) @ T_BASE_TARGET
COMMISSIONED = Truth(CAM, T_FLANGE_CAMERA)


def _world(reference: bool = False) -> tuple[SimulatedWorld[Truth], SimCamera, SimParts]:
    placements = [Placement(TARGET, T_BASE_TARGET)]
    if reference:
        placements.append(Placement(TARGET, REFERENCE, fixed_reference=True))
    parts = SimParts(placements, clock=lambda: 0.0)
    camera = SimCamera(CAM, parts, T_FLANGE_CAMERA, StaticPose(T_BASE_FLANGE0), seed=1,
                       noise_std=0.0)
    return SimulatedWorld(StillArm(), camera, parts, None, COMMISSIONED), camera, parts


def _expected_px(lens: CameraModel, T_flange_camera: Matrix4) -> NDArray[np.float64]:
    T_camera_target = invert_T(T_BASE_FLANGE0 @ T_flange_camera) @ T_BASE_TARGET
    pts = (T_camera_target[:3, :3] @ TARGET.points_mm.T).T + T_camera_target[:3, 3]
    return lens.project(pts)


def _error_px(image: NDArray[np.uint8], expected: NDArray[np.float64]) -> float:
    found = dot_centres(image)
    assert len(found) == TARGET.n_points, f"found {len(found)} dots"
    d = np.linalg.norm(expected[:, None, :] - found[None, :, :], axis=2)
    return float(d.min(axis=1).max())


def _frame(camera: SimCamera) -> NDArray[np.uint8]:
    camera._expose()
    exp = camera._latest
    assert exp is not None
    return camera._render(exp)


def test_a_knocked_camera_renders_from_its_new_mount_and_is_restored_exactly() -> None:
    world, camera, _ = _world()
    delta = T_from_pose([2.0, -1.0, 0.5], [0.0, 0.004, 0.0])
    world.set_faults(Faults(T_mount_delta=delta))
    knocked = T_FLANGE_CAMERA @ delta
    np.testing.assert_array_equal(world.truth_values().T_flange_camera, knocked)
    image = _frame(camera)
    assert _error_px(image, _expected_px(CAM, knocked)) < 0.5
    assert _error_px(image, _expected_px(CAM, T_FLANGE_CAMERA)) > 3.0
    world.clear_faults()
    assert world.truth_values() is COMMISSIONED
    np.testing.assert_array_equal(camera.optics()[1], T_FLANGE_CAMERA)
    assert _error_px(_frame(camera), _expected_px(CAM, T_FLANGE_CAMERA)) < 0.5


def test_a_shifted_lens_renders_through_the_new_intrinsics() -> None:
    world, camera, _ = _world()
    world.set_faults(Faults(focal_scale=1.01, principal_point_delta_px=(6.0, -4.0)))
    lens = world.truth_values().camera
    assert (lens.fx, lens.fy, lens.cx, lens.cy) == pytest.approx(
        (CAM.fx * 1.01, CAM.fy * 1.01, CAM.cx + 6.0, CAM.cy - 4.0))
    assert _error_px(_frame(camera), _expected_px(lens, T_FLANGE_CAMERA)) < 0.5
    world.clear_faults()
    assert world.truth_values().camera == CAM


def test_a_frame_exposed_before_a_fault_is_rendered_wholly_with_the_old_truth() -> None:
    world, camera, _ = _world()
    camera._expose()
    before = camera._latest
    assert before is not None
    world.set_faults(Faults(T_mount_delta=translation_T(5.0), focal_scale=1.02))
    assert _error_px(camera._render(before), _expected_px(CAM, T_FLANGE_CAMERA)) < 0.5
    after = _frame(camera)
    assert _error_px(after, _expected_px(world.truth_values().camera,
                                         T_FLANGE_CAMERA @ translation_T(5.0))) < 0.5


def test_a_fixed_reference_is_knocked_and_a_part_slipped_and_both_come_back() -> None:
    world, _, parts = _world(reference=True)
    knock = T_from_pose([0.5, 0.0, 0.0], [0.0, 0.0, 0.01])
    slip = translation_T(0.0, 3.0, 0.0)
    world.set_faults(Faults(T_reference_delta=knock, T_slip=slip))
    truth = parts.truth(0.0, T_BASE_FLANGE0, T_BASE_FLANGE0)
    np.testing.assert_allclose(truth[0].T_base_part, T_BASE_TARGET @ slip)
    np.testing.assert_allclose(truth[1].T_base_part, REFERENCE @ knock)
    assert truth[1].fixed_reference and not truth[0].fixed_reference
    np.testing.assert_allclose(world.true_T_base_target(), T_BASE_TARGET @ slip)
    world.clear_faults()
    truth = parts.truth(0.0, T_BASE_FLANGE0, T_BASE_FLANGE0)
    np.testing.assert_array_equal(truth[0].T_base_part, T_BASE_TARGET)
    np.testing.assert_array_equal(truth[1].T_base_part, REFERENCE)


def test_a_fault_the_world_cannot_take_changes_nothing() -> None:
    world, camera, parts = _world()
    mount = Faults(T_mount_delta=translation_T(1.0))
    world.set_faults(mount)
    for bad in (Faults(T_reference_delta=translation_T(1.0)),  # no fixed reference
                Faults(T_mount_delta=translation_T(2.0), slip_part=3,
                       T_slip=translation_T(1.0)),  # no part 3
                Faults(T_mount_delta=np.full((4, 4), np.nan))):
        with pytest.raises(ValueError):
            world.set_faults(bad)
        np.testing.assert_array_equal(camera.optics()[1], T_FLANGE_CAMERA @ translation_T(1.0))
        assert camera.optics()[0] == CAM
        np.testing.assert_array_equal(world.faults().T_mount_delta, translation_T(1.0))
        assert parts.slips() == {} and parts.reference_delta() is None


def test_a_fixed_reference_is_never_gripped() -> None:
    parts = SimParts([Placement(TARGET, T_BASE_TARGET, fixed_reference=True)],
                     clock=lambda: 0.0)
    assert parts.grip(0.0, T_BASE_FLANGE0, T_BASE_TARGET, 85.0, 0.0) is None
    with pytest.raises(ValueError, match="fixed reference"):
        parts.set_slip(0, translation_T(1.0))


def test_a_knocked_fixed_camera_renders_from_its_new_pose_in_the_base_frame() -> None:
    T_base_camera0 = T_BASE_FLANGE0 @ T_FLANGE_CAMERA
    parts = SimParts.one(TARGET, T_BASE_TARGET)
    away = T_from_pose([0.0, 0.0, 2000.0], [0.0, 0.0, 0.0])  # the tool far out of the view
    camera = FixedSimCamera(CAM, parts, T_base_camera0, StaticPose(away), np.eye(4),
                            tool_radius_mm=0.0, seed=1, noise_std=0.0)
    world = SimulatedWorld(StillArm(), camera, parts, None, Truth(CAM, T_base_camera0))
    delta = T_from_pose([1.5, 0.0, 0.0], [0.0, 0.0, 0.01])
    world.set_faults(Faults(T_mount_delta=delta))
    np.testing.assert_allclose(world.truth_values().T_flange_camera, T_base_camera0 @ delta)
    knocked = T_FLANGE_CAMERA @ delta  # the same camera pose, seen from the flange at rest
    assert _error_px(_frame(camera), _expected_px(CAM, knocked)) < 0.5
    world.clear_faults()
    np.testing.assert_array_equal(camera.T_base_camera, T_base_camera0)
    assert _error_px(_frame(camera), _expected_px(CAM, T_FLANGE_CAMERA)) < 0.5
