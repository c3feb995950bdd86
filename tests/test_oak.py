"""OAK adapter without a device: a host-only depthai pipeline feeds ImgFrames through the same
queues, callbacks and conversions the real device output goes through."""

from __future__ import annotations

import threading
import time
from collections.abc import Iterator
from typing import Any

import depthai as dai
import numpy as np
import pytest

from drivers.camera import Camera
from drivers.errors import ConnectionLostError, DeviceTimeoutError
from drivers.oak import CameraStatus, OakCamera, OakSession, OakSettings
from drivers.oak_calibration import (
    camera_model_from_calibration,
    offline_calibration,
    trim_distortion,
)

K_FULL = [[800.0, 0.0, 639.5], [0.0, 801.0, 399.5], [0.0, 0.0, 1.0]]
DIST = [0.1, -0.05, 0.001, 0.002, 0.01]


class HostSource(dai.node.ThreadedHostNode):
    """Stands in for dai.node.Camera: grey frames with sequence numbers and exposure times."""

    def __init__(self) -> None:
        super().__init__()
        self.out = self.createOutput()
        self.width, self.height, self.fps, self.exposure_us = 64, 40, 50.0, 4000
        self.skip: set[int] = set()
        self.alive = threading.Event()
        self.alive.set()
        self.sent_end_s: dict[int, float] = {}

    def run(self) -> None:
        seq = 0
        while self.isRunning():
            time.sleep(1.0 / self.fps)
            seq += 1
            if seq in self.skip or not self.alive.is_set():
                continue
            f = dai.ImgFrame()
            f.setCvFrame(np.full((self.height, self.width), seq % 256, np.uint8),
                         dai.ImgFrame.Type.GRAY8)
            f.setSequenceNum(seq)
            cam = f.cam
            cam.exposureTimeUs = self.exposure_us
            f.cam = cam
            end = dai.Clock.now()
            f.setTimestamp(end)
            self.sent_end_s[seq] = end.total_seconds()
            self.out.send(f)


class HostBackend:
    """Opens host-only pipelines; ``fail_next`` simulates an absent device."""

    def __init__(self, skip: set[int] | None = None) -> None:
        self.fail_next = 0
        self.skip = skip or set()
        self.sources: list[HostSource] = []
        self.pipelines: list[Any] = []

    def open(self, settings: OakSettings) -> OakSession:
        if self.fail_next > 0:
            self.fail_next -= 1
            raise RuntimeError("No available devices")
        p = dai.Pipeline(createImplicitDevice=False)
        src = p.create(HostSource)
        src.width, src.height, src.fps = settings.width, settings.height, settings.fps
        src.skip = self.skip
        self.sources.append(src)
        self.pipelines.append(p)
        calib = offline_calibration(settings.socket, K_FULL, 1280, 800, DIST)
        return OakSession(p, src.out, calib)


SETTINGS = OakSettings(width=64, height=40, fps=50.0, exposure_us=4000, stall_timeout_s=0.3,
                       backoff_initial_s=0.1, backoff_max_s=0.4)


@pytest.fixture
def backend() -> HostBackend:
    return HostBackend()


@pytest.fixture
def camera(backend: HostBackend) -> Iterator[OakCamera]:
    cam = OakCamera(SETTINGS, backend=backend)
    cam.connect()
    yield cam
    cam.disconnect()


def test_depthai_clock_is_time_monotonic() -> None:
    for _ in range(3):
        before = time.monotonic()
        dai_now = dai.Clock.now().total_seconds()
        after = time.monotonic()
        assert before - 1e-3 <= dai_now <= after + 1e-3


def test_calibration_scaled_to_the_output() -> None:
    calib = offline_calibration("CAM_B", K_FULL, 1280, 800, DIST)
    full = camera_model_from_calibration(calib, "CAM_B", 1280, 800)
    assert (full.fx, full.fy, full.cx, full.cy) == (800.0, 801.0, 639.5, 399.5)
    assert np.allclose(full.dist, DIST)
    half = camera_model_from_calibration(calib, "CAM_B", 640, 400)
    assert (half.fx, half.fy, half.width, half.height) == (400.0, 400.5, 640, 400)
    assert half.dist == full.dist
    with pytest.raises(ValueError, match="no factory calibration for CAM_C"):
        camera_model_from_calibration(calib, "CAM_C", 640, 400)
    with pytest.raises(ValueError, match="unknown camera socket"):
        camera_model_from_calibration(calib, "CAM_Z", 640, 400)


def test_calibration_survives_the_eeprom_json_round_trip() -> None:
    calib = offline_calibration("CAM_A", K_FULL, 1280, 800, DIST)
    again = dai.CalibrationHandler.fromJson(calib.eepromToJson())
    assert camera_model_from_calibration(again, "CAM_A", 1280, 800).fx == 800.0


def test_trim_distortion() -> None:
    assert trim_distortion([0.0] * 14) == ()
    assert trim_distortion([0.1, 0, 0, 0, 0] + [0.0] * 9) == (0.1, 0.0, 0.0, 0.0)
    assert len(trim_distortion([0.1, 0, 0, 0, 0.2] + [0.0] * 9)) == 5
    assert len(trim_distortion([0.0] * 6 + [0.3] + [0.0] * 7)) == 8


def test_settings_reject_bad_values() -> None:
    with pytest.raises(ValueError, match="exposure"):
        OakSettings(fps=60.0, exposure_us=20000)
    with pytest.raises(ValueError, match="socket"):
        OakSettings(socket="CAM_Z")
    with pytest.raises(ValueError, match="lens_position"):
        OakSettings(lens_position=300)


def test_is_a_camera(camera: OakCamera) -> None:
    assert isinstance(camera, Camera)
    assert camera.is_connected


def test_grey_frames_with_mid_exposure_timestamps(camera: OakCamera, backend: HostBackend) -> None:
    frame = camera.latest_frame(timeout_s=2.0)
    assert frame.image.shape == (40, 64) and frame.image.dtype == np.uint8
    assert int(frame.image[0, 0]) == frame.sequence % 256
    end_s = backend.sources[0].sent_end_s[frame.sequence]
    assert frame.timestamp_s == pytest.approx(end_s - 0.002, abs=1e-6)
    assert frame.timestamp_s < time.monotonic()
    assert frame.camera.width == 64 and frame.camera.fx == pytest.approx(40.0)


def test_freshest_frame_never_a_backlog(camera: OakCamera, backend: HostBackend) -> None:
    camera.latest_frame(timeout_s=2.0)
    time.sleep(0.4)  # ~20 frames arrive meanwhile
    newest_sent = max(backend.sources[0].sent_end_s)
    frame = camera.latest_frame()
    assert frame.sequence >= newest_sent - 1
    seqs = [camera.latest_frame().sequence for _ in range(5)]
    assert all(b > a for a, b in zip([frame.sequence, *seqs], seqs, strict=False))


def test_dropped_sequence_numbers_are_counted() -> None:
    backend = HostBackend(skip={5, 6, 10})
    cam = OakCamera(SETTINGS, backend=backend)
    cam.connect()
    try:
        while cam.latest_frame(timeout_s=2.0).sequence < 15:
            pass
        s = cam.status()
        assert s.dropped_frames == 3 and s.frames_received >= 12
    finally:
        cam.disconnect()


def test_timeout_when_frames_stop_briefly(camera: OakCamera, backend: HostBackend) -> None:
    camera.latest_frame(timeout_s=2.0)
    backend.sources[0].alive.clear()
    time.sleep(0.05)
    with pytest.raises(DeviceTimeoutError):
        camera.latest_frame(timeout_s=0.1)
    backend.sources[0].alive.set()


def _wait_for(cond: Any, timeout_s: float = 10.0) -> None:
    deadline = time.monotonic() + timeout_s
    while not cond():
        assert time.monotonic() < deadline, "condition not reached in time"
        time.sleep(0.02)


def test_stalled_device_reconnects_with_backoff() -> None:
    backend = HostBackend()
    seen: list[CameraStatus] = []
    cam = OakCamera(SETTINGS, backend=backend, on_status=seen.append)
    cam.connect()
    try:
        cam.latest_frame(timeout_s=2.0)
        backend.fail_next = 3  # the device is gone for three attempts
        backend.sources[0].alive.clear()
        _wait_for(lambda: cam.status().state == "reconnecting")
        with pytest.raises(ConnectionLostError, match="reconnecting"):
            cam.latest_frame()
        _wait_for(lambda: cam.status().state == "streaming")
        assert cam.latest_frame(timeout_s=2.0).sequence >= 1
        retries = [s.retry_in_s for s in seen if s.state == "reconnecting"]
        assert retries[:4] == [0.1, 0.2, 0.4, 0.4]  # doubling, capped
        assert cam.status().reconnects == 1 and len(backend.pipelines) == 2
        assert any("No available devices" in (s.last_error or "") for s in seen)
    finally:
        cam.disconnect()
    assert cam.status().state == "disconnected"


def test_stopped_pipeline_counts_as_device_loss(camera: OakCamera, backend: HostBackend) -> None:
    camera.latest_frame(timeout_s=2.0)
    backend.pipelines[0].stop()
    _wait_for(lambda: camera.status().reconnects == 1)
    assert camera.latest_frame(timeout_s=2.0).image.shape == (40, 64)


def test_connect_failure_is_connection_lost() -> None:
    backend = HostBackend()
    backend.fail_next = 1
    cam = OakCamera(SETTINGS, backend=backend)
    with pytest.raises(ConnectionLostError, match="No available devices"):
        cam.connect()
    assert cam.status().state == "disconnected" and not cam.is_connected
    with pytest.raises(ConnectionLostError):
        cam.latest_frame()
    cam.disconnect()  # safe without a connection


@pytest.mark.oak_hardware
def test_real_oak_streams_at_the_configured_rate() -> None:
    cam = OakCamera(OakSettings(width=640, height=400, fps=30.0))
    cam.connect()
    try:
        first = cam.latest_frame(timeout_s=5.0)
        frames = [cam.latest_frame(timeout_s=1.0) for _ in range(30)]
        span = frames[-1].timestamp_s - first.timestamp_s
        rate = (frames[-1].sequence - first.sequence) / span
        assert rate == pytest.approx(30.0, rel=0.1)
        assert abs(frames[-1].timestamp_s - time.monotonic()) < 0.2
        assert frames[-1].image.shape == (400, 640)
        assert cam.camera_model is not None and cam.camera_model.width == 640
    finally:
        cam.disconnect()
