"""Luxonis OAK camera adapter (depthai v3) behind :class:`drivers.camera.Camera`.

The device-specific part is one small backend (:class:`OakDeviceBackend`) that builds the
``dai.node.Camera`` with manual exposure, a fixed lens position (or autofocus when asked) and a
grey output at the configured size and rate. Settings changed while streaming
(:meth:`OakCamera.apply_settings`) go to the camera node's control input as
``dai.CameraControl`` messages, and are kept for the next reconnection.
Everything else (freshest-frame handling, mid-exposure timestamps, dropped sequence numbers,
intrinsics from the factory calibration, device-loss detection and reconnection with backoff)
lives in :class:`OakCamera` and works with any backend that hands over a pipeline and an output,
so it is tested with a host-only pipeline (``dai.Pipeline(createImplicitDevice=False)`` and a
``ThreadedHostNode`` producing ``ImgFrame``s).

Clocks: ``ImgFrame.getTimestamp()`` is on ``dai::Clock``, which is ``std::chrono::steady_clock``
with device timestamps already converted to host time by depthai's clock sync. On Linux that is
``CLOCK_MONOTONIC``, the clock of :func:`time.monotonic` (checked by tests/drivers/test_oak.py), so
timestamps need no offset. The raw timestamp marks the end of exposure;
``getTimestamp(CameraExposureOffset.MIDDLE)`` moves it to mid-exposure, which is the instant
the arm pose must be interpolated at.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, replace
from typing import Any, Literal, Protocol

import depthai as dai
import numpy as np
from numpy.typing import NDArray

from drivers.camera import CameraSettings, FocusSetting, Frame
from drivers.errors import ConnectionLostError, DeviceTimeoutError
from drivers.oak.calibration import board_socket, camera_model_from_calibration
from estimator import CameraModel

CameraState = Literal["disconnected", "connecting", "streaming", "reconnecting"]


@dataclass(frozen=True)
class OakSettings:
    """What the cell configures. ``focus`` is a lens position 0..255 or ``"auto"``; None leaves
    fixed-focus sensors (the OAK-D's mono pair) alone."""

    width: int = 1280
    height: int = 800
    fps: float = 30.0
    socket: str = "CAM_B"  # left mono sensor of an OAK-D; CAM_A on an OAK-1
    exposure_us: int = 2000
    iso: int = 400
    focus: FocusSetting | None = None
    device_id: str | None = None  # serial number or IP; None = the first device found
    stall_timeout_s: float = 2.0  # no frame for this long while streaming = device lost
    backoff_initial_s: float = 0.5
    backoff_max_s: float = 10.0

    def __post_init__(self) -> None:
        if self.width <= 0 or self.height <= 0:
            raise ValueError(f"output size must be positive, got {self.width}x{self.height}")
        if not 0 < self.fps <= 120:
            raise ValueError(f"fps must be within (0, 120], got {self.fps}")
        if not 1 <= self.exposure_us <= 1_000_000 / self.fps:
            raise ValueError(f"exposure_us must fit in a frame period, got {self.exposure_us}")
        if not 100 <= self.iso <= 1600:
            raise ValueError(f"iso must be within [100, 1600], got {self.iso}")
        if self.focus != "auto" and self.focus is not None and not 0 <= self.focus <= 255:
            raise ValueError(f"focus must be a lens position 0..255 or \"auto\", got {self.focus}")
        board_socket(self.socket)


@dataclass(frozen=True)
class CameraStatus:
    """What the cell shows while the camera streams, drops frames or reconnects."""

    state: CameraState
    frames_received: int = 0
    dropped_frames: int = 0  # gaps in the device's sequence numbers
    reconnects: int = 0
    last_error: str | None = None
    retry_in_s: float | None = None

    def as_dict(self) -> dict[str, object]:
        return dict(self.__dict__)


@dataclass
class OakSession:
    """One opened device: its running-to-be pipeline, the grey output and the calibration."""

    pipeline: Any  # dai.Pipeline
    output: Any  # dai.Node.Output
    calibration: Any  # dai.CalibrationHandler
    control: Any = None  # dai.Node.Input taking dai.CameraControl; None: settings are fixed


class OakBackend(Protocol):
    def open(self, settings: OakSettings) -> OakSession:
        """Build (not start) a pipeline; raise RuntimeError when the device is absent."""


class OakDeviceBackend:
    """The real device: ``dai.node.Camera`` with manual exposure and fixed focus."""

    def open(self, settings: OakSettings) -> OakSession:
        device = dai.Device(dai.DeviceInfo(settings.device_id)) if settings.device_id \
            else dai.Device()
        pipeline = dai.Pipeline(device)
        cam = pipeline.create(dai.node.Camera).build(board_socket(settings.socket))
        # Auto exposure would change blob contrast under us, and autofocus the intrinsics:
        # both only when the config asks for them.
        control_message(settings, initial=cam.initialControl)
        output = cam.requestOutput(
            (settings.width, settings.height), type=dai.ImgFrame.Type.GRAY8, fps=settings.fps,
            enableUndistortion=False,  # the estimator applies the factory distortion itself
        )
        return OakSession(pipeline, output, device.readCalibration(), cam.inputControl)


def control_message(settings: OakSettings, initial: Any = None) -> Any:
    """``settings``' exposure, gain and focus as a ``dai.CameraControl`` (or set on
    ``initial``, a node's ``initialControl``)."""
    ctrl = initial if initial is not None else dai.CameraControl()
    ctrl.setManualExposure(settings.exposure_us, settings.iso)
    if settings.focus == "auto":
        ctrl.setAutoFocusMode(dai.CameraControl.AutoFocusMode.CONTINUOUS_VIDEO)
    elif settings.focus is not None:
        ctrl.setManualFocus(settings.focus)
    return ctrl


def grey_image(img: Any) -> NDArray[np.uint8]:
    """The grey (luma) plane of an ImgFrame, copied out of depthai's buffer."""
    w, h = img.getWidth(), img.getHeight()
    kind = img.getType()
    if kind in (dai.ImgFrame.Type.GRAY8, dai.ImgFrame.Type.RAW8, dai.ImgFrame.Type.NV12):
        stride = img.getStride() or w
        data = np.asarray(img.getData(), dtype=np.uint8)
        return np.ascontiguousarray(data[: h * stride].reshape(h, stride)[:, :w])
    raise ValueError(f"unsupported image type {kind.name}: request GRAY8 or NV12")


def mid_exposure_s(img: Any) -> float:
    """Mid-exposure capture time on the host's ``time.monotonic()`` clock."""
    return float(img.getTimestamp(dai.CameraExposureOffset.MIDDLE).total_seconds())


class OakCamera:
    """:class:`drivers.camera.Camera` on an OAK, reconnecting on its own after device loss.

    ``on_status`` is called (from a background thread) on every state change, so the cell can
    show "camera lost, retrying in 2 s" instead of failing requests blindly.
    """

    def __init__(
        self, settings: OakSettings | None = None, *, backend: OakBackend | None = None,
        on_status: Callable[[CameraStatus], None] | None = None,
    ) -> None:
        self.settings = settings or OakSettings()
        self._backend = backend or OakDeviceBackend()
        self._on_status = on_status
        self._cond = threading.Condition()
        self._status = CameraStatus("disconnected")
        self._session: OakSession | None = None
        self._queue: Any = None
        self._control: Any = None  # input queue of the camera node's control input
        self._model: CameraModel | None = None
        self._latest: Any = None  # newest dai.ImgFrame
        self._latest_t = 0.0
        self._latest_n = 0  # arrival count of ``_latest``
        self._handed_out = 0  # arrival count of the last frame returned: none goes out twice
        self._last_seq: int | None = None
        self._stop = threading.Event()
        self._supervisor: threading.Thread | None = None

    # -- status ----------------------------------------------------------------------------
    def status(self) -> CameraStatus:
        with self._cond:
            return self._status

    def _set_status(self, **changes: Any) -> None:
        with self._cond:
            self._status = replace(self._status, **changes)
            status = self._status
            self._cond.notify_all()
        if self._on_status is not None:
            self._on_status(status)

    @property
    def is_connected(self) -> bool:
        return self.status().state == "streaming"

    def get_settings(self) -> CameraSettings:
        s = self.settings
        return CameraSettings(exposure_us=s.exposure_us, iso=s.iso, focus=s.focus)

    def apply_settings(self, settings: CameraSettings) -> CameraSettings:
        """Validate, send to the streaming device, and keep for reconnections.

        A value the OAK does not accept raises ValueError naming it, and nothing changes.
        """
        changes: dict[str, Any] = {}
        if settings.exposure_us is not None:
            changes["exposure_us"] = settings.exposure_us
        if settings.iso is not None:
            changes["iso"] = settings.iso
        if settings.focus is not None:
            changes["focus"] = settings.focus
        new = replace(self.settings, **changes)  # __post_init__ validates
        with self._cond:
            control = self._control
            if control is not None:
                control.send(control_message(new))
            self.settings = new
        return self.get_settings()

    @property
    def camera_model(self) -> CameraModel | None:
        """Intrinsics of the current output (None until the first connection)."""
        return self._model

    # -- lifecycle -------------------------------------------------------------------------
    def connect(self) -> None:
        if self._supervisor is not None:
            return
        self._set_status(state="connecting", last_error=None, retry_in_s=None)
        try:
            self._open()
        except (RuntimeError, ValueError) as err:
            self._set_status(state="disconnected", last_error=str(err))
            raise ConnectionLostError(f"cannot open the OAK camera: {err}") from err
        self._stop.clear()
        self._supervisor = threading.Thread(target=self._supervise, name="oak-supervisor",
                                            daemon=True)
        self._supervisor.start()

    def disconnect(self) -> None:
        self._stop.set()
        if self._supervisor is not None:
            self._supervisor.join(timeout=5.0)
            self._supervisor = None
        self._close()
        self._set_status(state="disconnected", retry_in_s=None)

    def _open(self) -> None:
        s = self.settings
        session = self._backend.open(s)
        try:
            model = camera_model_from_calibration(session.calibration, s.socket, s.width,
                                                  s.height)
            queue = session.output.createOutputQueue(maxSize=1, blocking=False)
            queue.addCallback(self._on_frame)
            control = None if session.control is None else session.control.createInputQueue()
            with self._cond:
                self._last_seq = None  # sequence numbers restart with the pipeline
                self._latest_t = time.monotonic()  # grace period for the first frame
            session.pipeline.start()
        except Exception:
            self._stop_pipeline(session)
            raise
        with self._cond:
            self._model, self._session, self._queue = model, session, queue
            self._control = control
        self._set_status(state="streaming", last_error=None, retry_in_s=None)

    def _close(self) -> None:
        with self._cond:
            self._control = None
        session, self._session, self._queue = self._session, None, None
        if session is not None:
            self._stop_pipeline(session)
        with self._cond:
            self._latest = None

    @staticmethod
    def _stop_pipeline(session: OakSession) -> None:
        try:
            if session.pipeline.isRunning():
                session.pipeline.stop()
                session.pipeline.wait()
        except RuntimeError:
            pass  # a lost device may refuse a clean stop; the pipeline is gone either way

    # -- frames ----------------------------------------------------------------------------
    def _on_frame(self, *args: Any) -> None:
        """depthai's queue callback (``(msg)`` or ``(name, msg)``): runs for every message."""
        msg = args[-1]
        if not isinstance(msg, dai.ImgFrame):
            return
        seq = msg.getSequenceNum()
        with self._cond:
            dropped = 0
            if self._last_seq is not None and seq > self._last_seq + 1:
                dropped = seq - self._last_seq - 1
            self._last_seq = seq
            self._latest, self._latest_t = msg, time.monotonic()
            self._latest_n += 1
            self._status = replace(
                self._status, frames_received=self._status.frames_received + 1,
                dropped_frames=self._status.dropped_frames + dropped,
            )
            self._cond.notify_all()

    def latest_frame(self, timeout_s: float = 1.0) -> Frame:
        """The newest frame not handed out before; waits up to ``timeout_s`` for one."""
        deadline = time.monotonic() + timeout_s
        with self._cond:
            while True:
                state = self._status.state
                if state != "streaming":
                    why = f": {self._status.last_error}" if self._status.last_error else ""
                    raise ConnectionLostError(f"OAK camera is {state}{why}")
                msg = self._latest
                if msg is not None and self._latest_n != self._handed_out:
                    self._handed_out = self._latest_n
                    break
                remaining = deadline - time.monotonic()
                if remaining <= 0:
                    raise DeviceTimeoutError(f"no frame from the OAK camera within {timeout_s} s")
                self._cond.wait(remaining)
        model = self._model
        assert model is not None
        image = grey_image(msg)
        if image.shape != (model.height, model.width):
            raise ConnectionLostError(
                f"OAK sent {image.shape[1]}x{image.shape[0]} frames, "
                f"configured {model.width}x{model.height}"
            )
        return Frame(image, mid_exposure_s(msg), int(msg.getSequenceNum()), model)

    # -- device loss -----------------------------------------------------------------------
    def _lost(self) -> str | None:
        session = self._session
        if session is None:
            return "no session"
        if not session.pipeline.isRunning():
            return "pipeline stopped (device lost)"
        with self._cond:
            silent = time.monotonic() - self._latest_t
        if silent > self.settings.stall_timeout_s:
            return f"no frames for {silent:.1f} s"
        return None

    def _supervise(self) -> None:
        s = self.settings
        while not self._stop.wait(0.05):
            reason = self._lost()
            if reason is None:
                continue
            self._close()
            backoff = s.backoff_initial_s
            self._set_status(state="reconnecting", last_error=reason, retry_in_s=backoff)
            while not self._stop.wait(backoff):
                try:
                    self._open()
                except (RuntimeError, ValueError) as err:
                    backoff = min(backoff * 2.0, s.backoff_max_s)
                    self._set_status(last_error=str(err), retry_in_s=backoff)
                    continue
                self._set_status(reconnects=self.status().reconnects + 1)
                break
