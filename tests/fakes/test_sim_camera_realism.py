"""What a real camera adds, measured against the simulated camera's own truth: latency,
timestamp error, motion blur and light flicker are there when asked for, absent by default."""

from __future__ import annotations

import time

import numpy as np
import pytest
from numpy.typing import NDArray

from estimator import CameraModel, Target
from estimator.transforms import T_from_pose, translation_T
from fakes.parts import SimParts
from fakes.render import motion_smear
from fakes.sim_camera import ExposureTruth, SimCamera

CAM = CameraModel(800.0, 800.0, 319.5, 239.5, (), 640, 480)
TARGET = Target([[0, 0, 0], [60, 0, 0], [100, 10, 0], [0, 50, 0], [40, 70, 0], [90, 60, 0]],
                10.0)
T_FLANGE_CAMERA = T_from_pose([0.0, 60.0, 40.0], [0.0, 0.0, 0.0])
T_BASE_FLANGE0 = T_from_pose([400.0, -100.0, 600.0], [np.pi, 0.0, 0.0])
T_BASE_TARGET = T_BASE_FLANGE0 @ T_FLANGE_CAMERA @ T_from_pose([-50.0, -35.0, 500.0],
                                                               [0.0, 0.0, 0.0])
REALISTIC_TIMING = {"latency_s": 0.033, "latency_jitter_s": 0.001,
                    "timestamp_offset_s": 0.002, "timestamp_jitter_s": 0.0002}


def _parts() -> SimParts:
    return SimParts.one(TARGET, T_BASE_TARGET)


def _static() -> tuple[NDArray[np.float64], float]:
    return T_BASE_FLANGE0, time.monotonic()


class _Sliding:
    """The flange moves along base x at ``speed_mm_s`` (the camera looks down: image x)."""

    def __init__(self, speed_mm_s: float) -> None:
        self.t0, self.speed = time.monotonic(), speed_mm_s

    def __call__(self) -> tuple[NDArray[np.float64], float]:
        now = time.monotonic()
        return translation_T(self.speed * (now - self.t0)) @ T_BASE_FLANGE0, now


def _frames(cam: SimCamera, n: int) -> list[tuple[int, float, float]]:
    """(sequence, timestamp, host time handed out) of ``n`` consecutive frames."""
    cam.connect()
    try:
        out = []
        for _ in range(n):
            f = cam.latest_frame(timeout_s=5.0)
            out.append((f.sequence, f.timestamp_s, time.monotonic()))
        return out
    finally:
        cam.disconnect()


def _truth(cam: SimCamera, sequence: int) -> ExposureTruth:
    return next(e for e in cam.exposure_log if e.sequence == sequence)


def test_ideal_frames_are_stamped_true_and_available_at_once() -> None:
    cam = SimCamera(CAM, _parts(), T_FLANGE_CAMERA, _static, seed=1)
    for seq, stamp, _ in _frames(cam, 8):
        e = _truth(cam, seq)
        assert stamp == e.true_time_s == e.available_s
        assert e.smear_px == (0.0, 0.0)


def test_latency_and_timestamp_error_follow_the_truth() -> None:
    cam = SimCamera(CAM, _parts(), T_FLANGE_CAMERA, _static, seed=1,
                    **REALISTIC_TIMING)  # type: ignore[arg-type]
    rows = _frames(cam, 15)
    errors = np.array([stamp - _truth(cam, seq).true_time_s for seq, stamp, _ in rows])
    assert errors.mean() == pytest.approx(0.002, abs=0.0003)
    assert 0.0 < errors.std() < 0.001
    for seq, _, handed_out in rows:
        e = _truth(cam, seq)
        assert 0.033 <= e.available_s - e.true_time_s < 0.045
        assert handed_out >= e.available_s  # no frame reaches the cell before it arrives


def test_motion_blur_smears_along_the_true_motion() -> None:
    speed, exposure = 500.0, 0.02  # 10 mm in the exposure at 500 mm: 16 px at f = 800
    blurred = SimCamera(CAM, _parts(), T_FLANGE_CAMERA, _Sliding(speed), seed=1,
                        exposure_s=exposure, motion_blur=True)
    seq = _frames(blurred, 3)[-1][0]
    dx, dy = _truth(blurred, seq).smear_px
    assert abs(dx) == pytest.approx(800.0 * speed * exposure / 500.0, rel=0.1)
    assert abs(dy) < 0.1 * abs(dx)
    sharp = SimCamera(CAM, _parts(), T_FLANGE_CAMERA, _Sliding(speed), seed=1,
                      exposure_s=exposure)
    assert _truth(sharp, _frames(sharp, 3)[-1][0]).smear_px == (0.0, 0.0)


def test_motion_smear_widens_by_the_smear_length() -> None:
    image = np.zeros((41, 81), np.uint8)
    image[:, 40] = 240  # a one-pixel line across the smear
    out = motion_smear(image, (16.0, 0.0)).astype(float)
    profile = out[20] / out[20].sum()
    x = np.arange(profile.size)
    var = float(((x - (profile * x).sum()) ** 2 * profile).sum())
    assert var == pytest.approx(16.0 ** 2 / 12.0, rel=0.15)  # a box of the smear's length
    assert motion_smear(image, (0.1, 0.0)) is image  # below a third of a pixel: untouched


def test_flicker_varies_the_gain_frame_to_frame() -> None:
    steady = SimCamera(CAM, _parts(), T_FLANGE_CAMERA, _static, seed=1,
                       exposure_jitter=0.0)
    gains = [_truth(steady, s).gain for s, _, _ in _frames(steady, 6)]
    assert gains == [1.0] * 6
    flicker = SimCamera(CAM, _parts(), T_FLANGE_CAMERA, _static, seed=1,
                        exposure_jitter=0.0, flicker_depth=0.1, flicker_hz=100.0)
    gains = [_truth(flicker, s).gain for s, _, _ in _frames(flicker, 12)]
    # 4 ms of a 10 ms flicker period: the mean over the exposure swings by up to ~7.6 %
    assert max(gains) - min(gains) > 0.03 and all(0.9 < g < 1.1 for g in gains)
