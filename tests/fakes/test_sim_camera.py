"""Simulated eye-in-hand camera: the image follows the arm, timestamps are mid-exposure, faults.

Dot centres are measured straight from the pixels (thresholded connected components) and
compared with the projection of the true target pose, so these tests do not depend on the
estimator; the closed-loop test at the end runs the real estimator against a moving sim arm.
"""

from __future__ import annotations

import itertools
import time
from collections.abc import Iterator

import cv2
import numpy as np
import pytest
from numpy.typing import NDArray

from drivers.camera import Camera, Frame
from drivers.errors import ConnectionLostError
from estimator import CameraModel, Estimator, Target
from estimator.transforms import T_from_pose, T_from_ur_pose, invert_T, translation_T
from fakes.parts import SimParts
from fakes.render import default_levels
from fakes.sim_arm import SimArm
from fakes.sim_camera import SimCamera

CAM = CameraModel(800.0, 800.0, 319.5, 239.5, (), 640, 480)
TARGET = Target([[0, 0, 0], [60, 0, 0], [100, 10, 0], [0, 50, 0], [40, 70, 0], [90, 60, 0]],
                10.0)
T_FLANGE_CAMERA = T_from_pose([0.0, 60.0, 40.0], [0.0, 0.0, 0.0])
T_CAMERA_TARGET0 = T_from_pose([-50.0, -35.0, 500.0], [0.05, -0.04, 0.0])
T_BASE_FLANGE0 = T_from_pose([400.0, -100.0, 600.0], [np.pi, 0.0, 0.0])
T_BASE_TARGET = T_BASE_FLANGE0 @ T_FLANGE_CAMERA @ T_CAMERA_TARGET0


def dot_centres(image: NDArray[np.uint8]) -> NDArray[np.float64]:
    _, dot = default_levels("dark")
    mask = (image < dot + 35).astype(np.uint8)  # below the background (110) and the plate
    n, _, stats, centroids = cv2.connectedComponentsWithStats(mask)
    keep = [i for i in range(1, n) if stats[i, cv2.CC_STAT_AREA] > 20]
    return np.asarray(centroids[keep], dtype=float).reshape(-1, 2)


def centre_error_px(frame: Frame, T_base_flange: NDArray[np.float64]) -> float:
    """Worst distance from each projected true dot centre to the nearest measured centre."""
    T_camera_target = invert_T(T_base_flange @ T_FLANGE_CAMERA) @ T_BASE_TARGET
    pts = (T_camera_target[:3, :3] @ TARGET.points_mm.T).T + T_camera_target[:3, 3]
    expected = frame.camera.project(pts)
    found = dot_centres(frame.image)
    assert len(found) == TARGET.n_points, f"found {len(found)} dots"
    d = np.linalg.norm(expected[:, None, :] - found[None, :, :], axis=2)
    return float(d.min(axis=1).max())


class StaticPose:
    def __init__(self, T: NDArray[np.float64]) -> None:
        self.T = T

    def __call__(self) -> tuple[NDArray[np.float64], float]:
        return self.T, time.monotonic()


class SlidingPose:
    """The flange moves along base x at ``speed_mm_s``; ``at(t)`` is the truth at time t."""

    def __init__(self, speed_mm_s: float) -> None:
        self.t0 = time.monotonic()
        self.speed = speed_mm_s

    def at(self, t: float) -> NDArray[np.float64]:
        return translation_T(self.speed * (t - self.t0)) @ T_BASE_FLANGE0

    def __call__(self) -> tuple[NDArray[np.float64], float]:
        now = time.monotonic()
        return self.at(now), now


def make_camera(pose_source: object, **kw: object) -> SimCamera:
    return SimCamera(CAM, SimParts.one(TARGET, T_BASE_TARGET), T_FLANGE_CAMERA, pose_source,  # type: ignore[arg-type]
                     seed=1, **kw)  # type: ignore[arg-type]


@pytest.fixture
def camera() -> Iterator[SimCamera]:
    cam = make_camera(StaticPose(T_BASE_FLANGE0), fps=20.0)
    cam.connect()
    yield cam
    cam.disconnect()


def test_is_a_camera(camera: SimCamera) -> None:
    assert isinstance(camera, Camera) and camera.is_connected


def test_frames_come_at_the_configured_rate(camera: SimCamera) -> None:
    frames = [camera.latest_frame(timeout_s=2.0) for _ in range(8)]
    seqs = [f.sequence for f in frames]
    assert all(b > a for a, b in itertools.pairwise(seqs))
    period = np.median(np.diff([f.timestamp_s for f in frames]) / np.diff(seqs))
    assert period == pytest.approx(1 / 20.0, rel=0.3)
    assert frames[-1].image.shape == (480, 640) and frames[-1].image.dtype == np.uint8
    assert frames[-1].timestamp_s <= time.monotonic()


def test_image_shows_the_target_where_it_is(camera: SimCamera) -> None:
    assert centre_error_px(camera.latest_frame(timeout_s=2.0), T_BASE_FLANGE0) < 0.5


def test_exposure_noise_differs_between_frames(camera: SimCamera) -> None:
    a = camera.latest_frame(timeout_s=2.0).image.astype(float)
    b = camera.latest_frame(timeout_s=2.0).image.astype(float)
    assert 0.5 < np.abs(a - b).mean() < 20


def test_timestamp_is_when_a_moving_arm_was_there() -> None:
    pose = SlidingPose(speed_mm_s=200.0)
    cam = make_camera(pose, fps=15.0)
    cam.connect()
    try:
        for _ in range(3):
            frame = cam.latest_frame(timeout_s=2.0)
            assert centre_error_px(frame, pose.at(frame.timestamp_s)) < 0.7
            # one frame period later the dots would be ~20 px away: the timestamp matters
            assert centre_error_px(frame, pose.at(frame.timestamp_s + 1 / 15.0)) > 10.0
    finally:
        cam.disconnect()


def test_target_pose_can_move_at_run_time(camera: SimCamera) -> None:
    moved = translation_T(0.0, 20.0) @ T_BASE_TARGET
    camera.parts.place_first(moved)
    frame = camera.latest_frame(timeout_s=2.0)
    frame = camera.latest_frame(timeout_s=2.0)
    shift = dot_centres(frame.image).mean(axis=0) - CAM.project(
        (T_CAMERA_TARGET0[:3, :3] @ TARGET.points_mm.T).T + T_CAMERA_TARGET0[:3, 3]).mean(axis=0)
    assert np.linalg.norm(shift) > 20.0  # 20 mm at 500 mm with f = 800 px: ~32 px
    with pytest.raises(ValueError):
        camera.parts.place_first(np.full((4, 4), np.nan))
    assert np.allclose(camera.parts.first_at(time.monotonic(), lambda: T_BASE_FLANGE0), moved)


def test_dropped_frames_leave_sequence_gaps(camera: SimCamera) -> None:
    first = camera.latest_frame(timeout_s=2.0)
    camera.drop_frames(2)
    time.sleep(0.01)
    nxt = camera.latest_frame(timeout_s=2.0)
    while nxt.sequence == first.sequence + 1:  # exposed before the drop was requested
        first, nxt = nxt, camera.latest_frame(timeout_s=2.0)
    assert nxt.sequence - first.sequence == 3 and camera.frames_dropped == 2


def test_lost_device_raises_until_restored(camera: SimCamera) -> None:
    camera.latest_frame(timeout_s=2.0)
    camera.set_lost(True)
    assert not camera.is_connected
    with pytest.raises(ConnectionLostError, match="lost"):
        camera.latest_frame()
    camera.set_lost(False)
    assert camera.is_connected
    assert camera.latest_frame(timeout_s=2.0).image.shape == (480, 640)


def test_connect_while_unplugged_fails() -> None:
    cam = make_camera(StaticPose(T_BASE_FLANGE0))
    cam.set_lost(True)
    with pytest.raises(ConnectionLostError):
        cam.connect()
    with pytest.raises(ConnectionLostError, match="not connected"):
        cam.latest_frame()


def test_blocked_view_is_dark_and_featureless(camera: SimCamera) -> None:
    camera.set_blocked(True)
    camera.latest_frame(timeout_s=2.0)
    img = camera.latest_frame(timeout_s=2.0).image
    assert img.mean() < 30 and img.std() < 5
    camera.set_blocked(False)
    camera.latest_frame(timeout_s=2.0)
    assert len(dot_centres(camera.latest_frame(timeout_s=2.0).image)) == 6


def test_failing_pose_source_is_connection_lost() -> None:
    def broken() -> tuple[NDArray[np.float64], float]:
        raise RuntimeError("controller shut down")

    cam = make_camera(broken)
    cam.connect()
    try:
        with pytest.raises(ConnectionLostError, match="controller shut down"):
            cam.latest_frame(timeout_s=2.0)
    finally:
        cam.disconnect()


def test_bad_settings_rejected() -> None:
    with pytest.raises(ValueError, match="fps"):
        make_camera(StaticPose(T_BASE_FLANGE0), fps=0.0)
    with pytest.raises(ValueError, match="exposure"):
        make_camera(StaticPose(T_BASE_FLANGE0), fps=100.0, exposure_s=0.02)


# -- closed loop: simulated arm + simulated camera + estimator -------------------------------

def test_closed_loop_estimator_sees_the_arm_move() -> None:
    est = Estimator(CAM, TARGET)

    def estimate(image: NDArray[np.uint8]) -> NDArray[np.float64]:
        return est.estimate(image).T_camera_target

    arm = SimArm()
    arm.connect()
    arm.power_on()
    try:
        def pose_source() -> tuple[NDArray[np.float64], float]:
            snap = arm.engine.snapshot()
            T = T_from_ur_pose(snap.tcp_pose) @ invert_T(T_from_ur_pose(snap.tcp_offset))
            return T, float(snap.host_monotonic_s)

        T_base_flange0, _ = pose_source()
        T_base_target = T_base_flange0 @ T_FLANGE_CAMERA @ T_CAMERA_TARGET0
        cam = SimCamera(CAM, SimParts.one(TARGET, T_base_target), T_FLANGE_CAMERA, pose_source,
                        fps=15.0, seed=3)
        cam.connect()
        try:
            before = estimate(cam.latest_frame(timeout_s=2.0).image)
            step = translation_T(30.0, -20.0, 10.0)
            arm.move_linear(step @ T_base_flange0, speed_mm_s=150.0, accel_mm_s2=1000.0)
            t_done = time.monotonic()
            frame = cam.latest_frame(timeout_s=2.0)
            while frame.timestamp_s < t_done:
                frame = cam.latest_frame(timeout_s=2.0)
            after = estimate(frame.image)
        finally:
            cam.disconnect()
    finally:
        arm.close()
    # The camera moved by `step` in the base frame; the target stayed where it was.
    T_base_camera0 = T_base_flange0 @ T_FLANGE_CAMERA
    T_base_camera1 = step @ T_base_camera0
    assert np.linalg.norm((T_base_camera0 @ before)[:3, 3] - T_base_target[:3, 3]) < 0.5
    assert np.linalg.norm((T_base_camera1 @ after)[:3, 3] - T_base_target[:3, 3]) < 0.5
    moved = np.linalg.norm(after[:3, 3] - before[:3, 3])
    assert moved == pytest.approx(np.linalg.norm([30.0, -20.0, 10.0]), abs=0.5)


class CountingPose(StaticPose):
    def __init__(self, T: NDArray[np.float64]) -> None:
        super().__init__(T)
        self.calls = 0

    def __call__(self) -> tuple[NDArray[np.float64], float]:
        self.calls += 1
        return super().__call__()


def test_a_resting_sensor_samples_rarely_and_wakes_with_a_fresh_frame(
        monkeypatch: pytest.MonkeyPatch) -> None:
    """Nobody takes frames: the sensor stops sampling the pose at frame rate; the next reader
    gets an exposure made after it asked, not the resting sensor's old one."""
    import fakes.sim_camera as sim_camera

    monkeypatch.setattr(sim_camera, "IDLE_AFTER_S", 0.3)
    pose = CountingPose(T_BASE_FLANGE0)
    cam = make_camera(pose, fps=60.0)
    cam.connect()
    try:
        cam.latest_frame(timeout_s=2.0)
        time.sleep(0.6)  # 0.3 s streaming, then resting
        before = pose.calls
        time.sleep(1.0)
        resting_calls = pose.calls - before
        asked_s = time.monotonic()
        frame = cam.latest_frame(timeout_s=2.0)
        assert resting_calls <= 1.0 / sim_camera.IDLE_PERIOD_S + 1  # 60 while streaming
        assert frame.timestamp_s >= asked_s
        assert centre_error_px(frame, T_BASE_FLANGE0) < 0.5
        nxt = cam.latest_frame(timeout_s=2.0)  # streaming again: the next one comes at rate
        assert nxt.sequence == frame.sequence + 1
        assert nxt.timestamp_s - frame.timestamp_s == pytest.approx(1 / 60.0, abs=0.05)
    finally:
        cam.disconnect()
