"""Which camera intrinsics the cell computes with: its configured ones, or the device's.

A camera reports intrinsics with every frame (an OAK its factory calibration, the simulated
camera the calibration it was given). They are a calibration like any other and can be wrong:
a commissioning-day intrinsics calibration written into ``[camera]`` must win over them, or
the calibration would be silently undone by the device. So by default (``[camera] intrinsics =
"config"``) the cell uses the configured values and says once, with the size of the
difference, when the device reports others; ``"device"`` trusts the device's.

A frame whose size differs from ``[camera] width x height`` cannot use the configured values
(they are for another resolution); its own are used then, with a warning.
"""

from __future__ import annotations

import logging
import threading
from typing import Literal

from estimator import CameraModel

log = logging.getLogger(__name__)

IntrinsicsSource = Literal["config", "device"]


def describe_difference(device: CameraModel, configured: CameraModel) -> str:
    """The device's intrinsics against the configured ones, in the units an integrator
    compares them in."""
    focal_pct = 100.0 * max(abs(device.fx / configured.fx - 1.0),
                            abs(device.fy / configured.fy - 1.0))
    centre_px = max(abs(device.cx - configured.cx), abs(device.cy - configured.cy))
    same_dist = tuple(device.dist) == tuple(configured.dist)
    return (f"focal {focal_pct:.2f} %, principal point {centre_px:.1f} px, distortion "
            f"{'the same' if same_dist else 'different'}")


class IntrinsicsPolicy:
    """Maps the intrinsics a frame carries to the ones the cell computes with."""

    def __init__(self, configured: CameraModel, source: IntrinsicsSource = "config") -> None:
        self.configured = configured
        self.source = source
        self._warned: set[CameraModel] = set()
        self._lock = threading.Lock()

    def model_for(self, device: CameraModel) -> CameraModel:
        """The intrinsics to use for a frame that reports ``device``."""
        if device == self.configured:
            return device
        if (device.width, device.height) != (self.configured.width, self.configured.height):
            self._warn_once(device, f"frames are {device.width}x{device.height}, [camera] says "
                            f"{self.configured.width}x{self.configured.height}: using the "
                            "device's intrinsics for that size")
            return device
        if self.source == "device":
            self._warn_once(device, "camera intrinsics differ from [camera] ("
                            f"{describe_difference(device, self.configured)}); using the "
                            "device's ([camera] intrinsics = \"device\")")
            return device
        self._warn_once(device, "the camera reports other intrinsics than [camera] ("
                        f"{describe_difference(device, self.configured)}); using [camera]'s "
                        "(set [camera] intrinsics = \"device\" to use the device's)")
        return self.configured

    def _warn_once(self, device: CameraModel, message: str) -> None:
        with self._lock:
            if device in self._warned:
                return
            self._warned.add(device)
        log.warning(message)
