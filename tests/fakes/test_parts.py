"""The simulated world's parts: the grasp tolerance, the fingers stopping on a part (gOBJ 2)
or closing on nothing (gOBJ 3) on the fake's own clock, a held part riding on the flange,
released where it is, and overlapping parts rendered nearer over farther."""

from __future__ import annotations

import numpy as np
import pytest
from numpy.typing import NDArray

from drivers.robotiq import GOBJ_AT_REQUEST, GOBJ_CONTACT_CLOSING, RACT, RGTO
from estimator import CameraModel
from estimator.transforms import T_from_pose, invert_T, pose_distance, translation_T
from fakes.gripper import GripperModel, opening_mm
from fakes.parts import (
    GRASP_AXIAL_MM,
    GRASP_LATERAL_MM,
    GRASP_TILT_DEG,
    Placement,
    SimParts,
    in_grasp,
)
from fakes.render import default_levels, grid_target, render_scene

T_FLANGE_TCP = translation_T(0.0, 0.0, 150.0)
PART = T_from_pose([-400.0, -100.0, 30.0], [np.pi, 0.0, 0.0])
LAYOUT = grid_target(3, 4, 15.0, 6.0)


def test_the_grasp_tolerance_is_the_documented_one() -> None:
    assert in_grasp(PART, PART)
    assert in_grasp(PART, PART @ translation_T(GRASP_LATERAL_MM - 0.1, 0.0, 0.0))
    assert not in_grasp(PART, PART @ translation_T(0.0, GRASP_LATERAL_MM + 0.1, 0.0))
    assert in_grasp(PART, PART @ translation_T(0.0, 0.0, -(GRASP_AXIAL_MM - 0.1)))
    assert not in_grasp(PART, PART @ translation_T(0.0, 0.0, GRASP_AXIAL_MM + 0.1))
    assert in_grasp(PART, PART @ T_from_pose([0, 0, 0], [np.radians(GRASP_TILT_DEG - 0.1), 0, 0]))
    assert not in_grasp(PART, PART @ T_from_pose([0, 0, 0],
                                                 [0, np.radians(GRASP_TILT_DEG + 0.1), 0]))
    assert in_grasp(PART, PART @ T_from_pose([0, 0, 0], [0, 0, 2.0]))  # the turn is free


class Clock:
    def __init__(self) -> None:
        self.t = 100.0

    def __call__(self) -> float:
        return self.t


class Arm:
    """A flange the test moves by hand; the grasp reads where it is."""

    def __init__(self, parts: SimParts, clock: Clock) -> None:
        self.parts, self.clock = parts, clock
        self.T_flange = PART @ invert_T(T_FLANGE_TCP)

    def grip(self, opening: float, closing_to: float) -> float | None:
        return self.parts.grip(self.clock(), self.T_flange, self.T_flange @ T_FLANGE_TCP,
                               opening, closing_to)

    def release(self) -> None:
        self.parts.release(self.clock(), self.T_flange)


def _close(model: GripperModel, clock: Clock, position: int = 0xFF) -> list[int]:
    model.write_request(0, [(RACT | RGTO) << 8, position, (255 << 8) | 255])
    clock.t += 2.0
    return model.status_bytes()


def _activated(clock: Clock, arm: Arm) -> GripperModel:
    model = GripperModel(activation_time_s=0.1, grasp=arm, clock=clock)
    model.write_request(0, [RACT << 8, 0, 0])
    clock.t += 0.2
    return model


def test_the_fingers_stop_on_the_part_at_the_tcp_and_carry_it() -> None:
    clock = Clock()
    parts = SimParts([Placement(LAYOUT, PART), Placement(LAYOUT, translation_T(200.0) @ PART,
                                                         width_mm=25.0)], 40.0, clock)
    arm = Arm(parts, clock)
    model = _activated(clock, arm)
    status = _close(model, clock)
    assert status[0] >> 6 == GOBJ_CONTACT_CLOSING
    assert opening_mm(status[4]) == pytest.approx(40.0, abs=0.34)
    held = parts.truth(clock(), arm.T_flange, arm.T_flange @ T_FLANGE_TCP)
    assert [p.held for p in held] == [True, False]
    arm.T_flange = translation_T(10.0, -20.0, 100.0) @ arm.T_flange  # the arm lifts it
    clock.t += 1.0
    moved = parts.truth(clock(), arm.T_flange, arm.T_flange @ T_FLANGE_TCP)[0].T_base_part
    assert pose_distance(moved, translation_T(10.0, -20.0, 100.0) @ PART)[0] < 1e-9
    status = _close(model, clock, position=0x00)  # open: let go
    assert opening_mm(status[4]) == 85.0
    arm.T_flange = translation_T(0.0, 0.0, 100.0) @ arm.T_flange
    after = parts.truth(clock(), arm.T_flange, arm.T_flange @ T_FLANGE_TCP)[0]
    assert not after.held and pose_distance(after.T_base_part, moved)[0] < 1e-9


def test_closing_on_nothing_closes_fully() -> None:
    clock = Clock()
    parts = SimParts([Placement(LAYOUT, PART)], 40.0, clock)
    arm = Arm(parts, clock)
    arm.T_flange = translation_T(0.0, 8.0) @ arm.T_flange  # 8 mm beside the part
    status = _close(_activated(clock, arm), clock)
    assert status[0] >> 6 == GOBJ_AT_REQUEST and status[4] == 0xFF
    assert not parts.truth(clock(), arm.T_flange, arm.T_flange)[0].held


def test_a_part_on_a_conveyor_is_taken_where_it_has_drifted_to() -> None:
    clock = Clock()
    parts = SimParts([Placement(LAYOUT, translation_T(-50.0) @ PART,
                                velocity_mm_s=np.array([10.0, 0.0, 0.0]))], 40.0, clock)
    arm = Arm(parts, clock)
    clock.t += 5.0  # 50 mm later it lies at the grasp pose
    status = _close(_activated(clock, arm), clock)
    assert status[0] >> 6 == GOBJ_CONTACT_CLOSING
    truth = parts.truth(clock(), arm.T_flange, arm.T_flange @ T_FLANGE_TCP)[0]
    assert truth.held and not np.any(truth.velocity_mm_s)


def test_bad_placements_change_nothing() -> None:
    parts = SimParts([Placement(LAYOUT, PART)])
    for bad in ([], [Placement(LAYOUT, np.full((4, 4), np.nan))],
                [Placement(LAYOUT, PART, width_mm=90.0)]):
        with pytest.raises(ValueError):
            parts.place(bad)
    assert pose_distance(parts.first_at(0.0, lambda: np.eye(4)), PART)[0] == 0.0


def _dark(image: NDArray[np.uint8], px: NDArray[np.float64]) -> bool:
    x, y = np.round(px).astype(int)
    return bool(image[y, x] < (default_levels("dark")[1] + default_levels("dark")[0]) / 2)


def test_overlapping_parts_render_nearer_over_farther() -> None:
    cam = CameraModel(800.0, 800.0, 319.5, 239.5, (), 640, 480)
    near = T_from_pose([-40.0, -20.0, 400.0], [0.0, 0.0, 0.0])
    far = T_from_pose([-10.0, -10.0, 500.0], [0.0, 0.0, 0.3])
    image = render_scene(cam, [(LAYOUT, far), (LAYOUT, near)], noise_std=0.0,
                         lighting_gradient=0.0, rng=np.random.default_rng(0))
    again = render_scene(cam, [(LAYOUT, near), (LAYOUT, far)], noise_std=0.0,
                         lighting_gradient=0.0, rng=np.random.default_rng(0))
    assert np.array_equal(image, again)  # the order drawn is the depth's, not the list's

    def centres(T: NDArray[np.float64]) -> NDArray[np.float64]:
        return cam.project(LAYOUT.points_mm @ T[:3, :3].T + T[:3, 3])

    assert all(_dark(image, p) for p in centres(near))  # every near dot shows
    near_plate = cv_hull(centres(near))
    clear = [p for p in centres(far)  # off every near dot, where only the plate can be
             if np.linalg.norm(centres(near) - p, axis=1).min() > 12.0]
    hidden = [p for p in clear if inside(near_plate, p)]
    # the near plate reaches 2 dot diameters (12 mm: 24 px at 400 mm) beyond its dots
    shown = [p for p in centres(far) if not inside(near_plate, p, margin=-35.0)]
    assert hidden and shown
    assert not any(_dark(image, p) for p in hidden)  # under the near plate
    assert all(_dark(image, p) for p in shown)


def cv_hull(px: NDArray[np.float64]) -> NDArray[np.float32]:
    import cv2

    return np.asarray(cv2.convexHull(px.astype(np.float32)), dtype=np.float32)


def inside(hull: NDArray[np.float32], p: NDArray[np.float64], margin: float = 0.0) -> bool:
    import cv2

    return bool(cv2.pointPolygonTest(hull, (float(p[0]), float(p[1])), True) >= margin)
