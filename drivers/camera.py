"""The camera interface: the smallest surface the cell needs from an image source."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal, Protocol, runtime_checkable

import numpy as np
from numpy.typing import NDArray

from estimator import CameraModel


@dataclass(frozen=True)
class Frame:
    """One grey image with when it was taken and the intrinsics valid for it."""

    image: NDArray[np.uint8]  # HxW, 8-bit grey
    timestamp_s: float  # host time.monotonic() at mid-exposure
    sequence: int  # device frame counter; gaps mean dropped frames
    camera: CameraModel


FocusSetting = int | Literal["auto"]


@dataclass(frozen=True)
class CameraSettings:
    """Sensor settings an operator or the config may change while the camera runs.

    ``None`` means "not set here": in a request, leave that setting as it is; in what a camera
    reports, the camera has no such control (a fixed-focus sensor reports ``focus=None``).
    ``exposure_us`` and ``iso`` together fix the exposure (manual); ``focus`` is a lens
    position 0..255 or ``"auto"``.
    """

    exposure_us: int | None = None
    iso: int | None = None
    focus: FocusSetting | None = None


@runtime_checkable
class Camera(Protocol):
    """An image source. Implementations: OAK (drivers.oak.camera), simulated (fakes.sim_camera)."""

    def connect(self) -> None:
        """Open the device and start streaming; raises ConnectionLostError when it cannot."""

    def latest_frame(self, timeout_s: float = 1.0) -> Frame:
        """The freshest frame (never a stale backlog); DeviceTimeoutError when none arrives."""

    def disconnect(self) -> None:
        """Stop streaming and release the device. Safe to call twice."""

    @property
    def is_connected(self) -> bool:
        """True while frames are flowing."""

    def get_settings(self) -> CameraSettings:
        """The settings in force (None for a control the camera does not have)."""

    def apply_settings(self, settings: CameraSettings) -> CameraSettings:
        """Change the settings given (None fields are left alone) and return those in force.

        ValueError names the setting when a value is outside what the camera accepts; then
        nothing changes.
        """
