"""The camera interface: the smallest surface the cell needs from an image source."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol, runtime_checkable

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


@runtime_checkable
class Camera(Protocol):
    """An image source. Implementations: OAK (drivers.oak), simulated (fakes.sim_camera)."""

    def connect(self) -> None:
        """Open the device and start streaming; raises ConnectionLostError when it cannot."""

    def latest_frame(self, timeout_s: float = 1.0) -> Frame:
        """The freshest frame (never a stale backlog); DeviceTimeoutError when none arrives."""

    def disconnect(self) -> None:
        """Stop streaming and release the device. Safe to call twice."""

    @property
    def is_connected(self) -> bool:
        """True while frames are flowing."""
