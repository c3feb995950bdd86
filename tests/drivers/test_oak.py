"""OAK adapter without a device: a host-only depthai pipeline feeds ImgFrames through the same
queues, callbacks and conversions the real device output goes through."""

from __future__ import annotations

import threading
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import depthai as dai
import numpy as np
import pytest

from drivers.camera import Camera, CameraSettings
from drivers.errors import ConnectionLostError, DeviceTimeoutError
from drivers.oak.calibration import (
    camera_model_from_calibration,
    offline_calibration,
    trim_distortion,
)
from drivers.oak.camera import CameraStatus, OakCamera, OakSession, OakSettings
from tests.support.paths import REPO
from tests.support.waiting import wait_until

K_FULL = [[800.0, 0.0, 639.5], [0.0, 801.0, 399.5], [0.0, 0.0, 1.0]]
DIST = [0.1, -0.05, 0.001, 0.002, 0.01]


class HostSource(dai.node.ThreadedHostNode):
    """Stands in for dai.node.Camera: grey frames with sequence numbers and exposure times."""

    def __init__(self) -> None:
        super().__init__()
        self.out = self.createOutput()
        self.control = self.createInput()  # like dai.node.Camera's inputControl
        self.width, self.height, self.fps, self.exposure_us = 64, 40, 50.0, 4000
        self.iso, self.lens_position, self.autofocus = 400, 0, False
        self.controls: list[Any] = []
        self.skip: set[int] = set()
        self.alive = threading.Event()
        self.alive.set()
        self.sent_end_s: dict[int, float] = {}

    def run(self) -> None:
        seq = 0
        while self.isRunning():
            time.sleep(1.0 / self.fps)
            seq += 1
            self._apply_controls()
            if seq in self.skip or not self.alive.is_set():
                continue
            f = dai.ImgFrame()
            f.setCvFrame(np.full((self.height, self.width), seq % 256, np.uint8),
                         dai.ImgFrame.Type.GRAY8)
            f.setSequenceNum(seq)
            cam = f.cam
            cam.exposureTimeUs = self.exposure_us
            cam.sensitivityIso = self.iso
            cam.lensPosition = self.lens_position
            f.cam = cam
            end = dai.Clock.now()
            f.setTimestamp(end)
            self.sent_end_s[seq] = end.total_seconds()
            self.out.send(f)


    def _apply_controls(self) -> None:
        """What the sensor does with CameraControl messages: the next frames show them."""
        C = dai.CameraControl.Command
        while (ctrl := self.control.tryGet()) is not None:
            self.controls.append(ctrl)
            if ctrl.getCommand(C.AE_MANUAL):
                self.exposure_us = round(ctrl.getExposureTime().total_seconds() * 1e6)
                self.iso = ctrl.getSensitivity()
            if ctrl.getCommand(C.MOVE_LENS):
                self.lens_position, self.autofocus = ctrl.getLensPosition(), False
            if ctrl.getCommand(C.AF_MODE):
                self.autofocus = (ctrl.autoFocusMode
                                  == dai.CameraControl.AutoFocusMode.CONTINUOUS_VIDEO)


class HostBackend:
    """Opens host-only pipelines; ``fail_next`` simulates an absent device."""

    def __init__(self, skip: set[int] | None = None) -> None:
        self.fail_next = 0
        self.skip = skip or set()
        self.sources: list[HostSource] = []
        self.pipelines: list[Any] = []
        self.opened: list[OakSettings] = []

    def open(self, settings: OakSettings) -> OakSession:
        if self.fail_next > 0:
            self.fail_next -= 1
            raise RuntimeError("No available devices")
        p = dai.Pipeline(createImplicitDevice=False)
        src = p.create(HostSource)
        src.width, src.height, src.fps = settings.width, settings.height, settings.fps
        src.exposure_us, src.iso = settings.exposure_us, settings.iso  # the initial control
        src.lens_position = settings.focus if isinstance(settings.focus, int) else 0
        src.autofocus = settings.focus == "auto"
        src.skip = self.skip
        self.sources.append(src)
        self.pipelines.append(p)
        self.opened.append(settings)
        calib = offline_calibration(settings.socket, K_FULL, 1280, 800, DIST)
        return OakSession(p, src.out, calib, src.control)


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
    with pytest.raises(ValueError, match="focus"):
        OakSettings(focus=300)
    with pytest.raises(ValueError, match="iso"):
        OakSettings(iso=50)
    assert OakSettings(focus="auto").focus == "auto"


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


def test_stalled_device_reconnects_with_backoff() -> None:
    backend = HostBackend()
    seen: list[CameraStatus] = []
    cam = OakCamera(SETTINGS, backend=backend, on_status=seen.append)
    cam.connect()
    try:
        cam.latest_frame(timeout_s=2.0)
        backend.fail_next = 3  # the device is gone for three attempts
        backend.sources[0].alive.clear()
        wait_until(lambda: cam.status().state == "reconnecting")
        with pytest.raises(ConnectionLostError, match="reconnecting"):
            cam.latest_frame()
        wait_until(lambda: cam.status().state == "streaming")
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
    wait_until(lambda: camera.status().reconnects == 1)
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


def _wait_frame(cam: OakCamera, cond: Any, timeout_s: float = 5.0) -> dai.ImgFrame:
    """The newest depthai frame once ``cond(frame)`` holds (the control took effect)."""
    deadline = time.monotonic() + timeout_s
    while True:
        cam.latest_frame(timeout_s=2.0)
        msg = cam._latest
        if msg is not None and cond(msg):
            return msg
        assert time.monotonic() < deadline, "the setting never reached the frames"


def test_apply_settings_reaches_the_streaming_sensor(camera: OakCamera,
                                                     backend: HostBackend) -> None:
    assert camera.get_settings() == CameraSettings(exposure_us=4000, iso=400, focus=None)
    in_force = camera.apply_settings(CameraSettings(exposure_us=1500, iso=800, focus=120))
    assert in_force == CameraSettings(exposure_us=1500, iso=800, focus=120)
    msg = _wait_frame(camera, lambda m: m.cam.exposureTimeUs == 1500)
    assert msg.cam.sensitivityIso == 800 and msg.cam.lensPosition == 120
    # mid-exposure moves with the exposure: 0.75 ms before the end now
    frame = camera.latest_frame(timeout_s=2.0)
    end_s = backend.sources[0].sent_end_s[frame.sequence]
    assert frame.timestamp_s == pytest.approx(end_s - 0.00075, abs=1e-6)
    camera.apply_settings(CameraSettings(focus="auto"))
    _wait_frame(camera, lambda m: backend.sources[0].autofocus)
    assert camera.get_settings().focus == "auto"


def test_rejected_settings_change_nothing(camera: OakCamera, backend: HostBackend) -> None:
    before = camera.get_settings()
    with pytest.raises(ValueError, match="exposure_us"):
        camera.apply_settings(CameraSettings(exposure_us=50_000))  # longer than 1/50 s
    with pytest.raises(ValueError, match="iso"):
        camera.apply_settings(CameraSettings(iso=20))
    with pytest.raises(ValueError, match="focus"):
        camera.apply_settings(CameraSettings(focus=999))
    assert camera.get_settings() == before
    camera.latest_frame(timeout_s=2.0)
    assert backend.sources[0].controls == []  # nothing was sent to the device


def test_settings_survive_a_reconnection(camera: OakCamera, backend: HostBackend) -> None:
    camera.apply_settings(CameraSettings(exposure_us=3000))
    backend.pipelines[0].stop()
    wait_until(lambda: camera.status().reconnects == 1)
    assert backend.opened[-1].exposure_us == 3000
    msg = _wait_frame(camera, lambda m: True)
    assert msg.cam.exposureTimeUs == 3000


def test_settings_before_connect_are_used_on_connect() -> None:
    backend = HostBackend()
    cam = OakCamera(SETTINGS, backend=backend)
    cam.apply_settings(CameraSettings(iso=1200))
    cam.connect()
    try:
        assert _wait_frame(cam, lambda m: True).cam.sensitivityIso == 1200
    finally:
        cam.disconnect()


def test_config_camera_settings_reach_the_oak_adapter(tmp_path: Path) -> None:
    """[camera] device id, socket, size, fps, exposure, iso and focus -> the adapter -> the
    host-only pipeline's frames."""
    from cell.config.devices import OakCameraConfig
    from cell.config.schema import load_config
    from cell.devices.factory import oak_settings

    text = (REPO / "cell" / "configs" / "real-cell.example.toml").read_text()
    text = text.replace("width = 1280", "width = 64").replace("height = 800", "height = 40")
    text = text.replace("fps = 15.0", "fps = 40.0").replace('device_id = ""',
                                                              'device_id = "14442C10D13EABCE00"')
    text = text.replace('socket = "CAM_B"', 'socket = "CAM_A"')
    text = text.replace("exposure_us = 2000", "exposure_us = 3500").replace("iso = 400",
                                                                            "iso = 640")
    text = text.replace("# focus = 130", "focus = 130")
    (tmp_path / "cell.toml").write_text(text)
    camera = load_config(tmp_path / "cell.toml").camera
    assert isinstance(camera, OakCameraConfig)
    settings = oak_settings(camera)
    assert (settings.width, settings.height, settings.fps) == (64, 40, 40.0)
    assert settings.device_id == "14442C10D13EABCE00" and settings.socket == "CAM_A"
    assert (settings.exposure_us, settings.iso, settings.focus) == (3500, 640, 130)
    backend = HostBackend()
    cam = OakCamera(settings, backend=backend)
    cam.connect()
    try:
        msg = _wait_frame(cam, lambda m: True)
        assert (msg.cam.exposureTimeUs, msg.cam.sensitivityIso, msg.cam.lensPosition) == \
            (3500, 640, 130)
        assert cam.latest_frame(timeout_s=2.0).image.shape == (40, 64)
        assert cam.get_settings() == CameraSettings(exposure_us=3500, iso=640, focus=130)
    finally:
        cam.disconnect()
