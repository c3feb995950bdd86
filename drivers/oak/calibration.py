"""OAK factory calibration -> :class:`estimator.CameraModel` for one output stream.

Every OAK leaves the factory with per-sensor intrinsics and distortion in its EEPROM; depthai's
``CalibrationHandler`` rescales the intrinsics to a requested output size (its own convention
for the principal point, which we keep: it is the device maker's statement of the geometry).
Kept apart from the streaming code so it can be tested with an offline handler built from an
EEPROM structure, with no device attached.
"""

from __future__ import annotations

from typing import Any

import depthai as dai

from estimator import CameraModel

_OPENCV_LENGTHS = (4, 5, 8, 12, 14)


def board_socket(name: str) -> Any:
    """``"CAM_B"`` -> ``dai.CameraBoardSocket.CAM_B``; a clear ValueError for a typo."""
    try:
        return dai.CameraBoardSocket.__members__[name]
    except KeyError:
        names = ", ".join(n for n in dai.CameraBoardSocket.__members__ if n.startswith("CAM_"))
        raise ValueError(f"unknown camera socket {name!r}; use one of {names}") from None


def trim_distortion(coeffs: list[float]) -> tuple[float, ...]:
    """Shortest OpenCV-valid prefix that keeps every non-zero coefficient (() if all zero)."""
    last = max((i for i, c in enumerate(coeffs) if c != 0.0), default=-1)
    if last < 0:
        return ()
    n = next(n for n in _OPENCV_LENGTHS if n > last)
    return tuple(float(c) for c in coeffs[:n])


def camera_model_from_calibration(
    calib: Any, socket: str, width: int, height: int
) -> CameraModel:
    """Intrinsics and distortion of ``socket`` as seen in a ``width`` x ``height`` output.

    Raises ValueError when the EEPROM has no intrinsics for that socket or uses a lens model
    the estimator cannot apply (only OpenCV's perspective model is supported).
    """
    sock = board_socket(socket)
    try:
        K = calib.getCameraIntrinsics(sock, width, height)
        coeffs = list(calib.getDistortionCoefficients(sock))
        model = calib.getDistortionModel(sock)
    except RuntimeError as err:
        raise ValueError(f"the device has no factory calibration for {socket}: {err}") from err
    if model != dai.CameraModel.Perspective:
        raise ValueError(
            f"{socket} uses the {model.name} lens model; only Perspective is supported"
        )
    return CameraModel(
        fx=float(K[0][0]), fy=float(K[1][1]), cx=float(K[0][2]), cy=float(K[1][2]),
        dist=trim_distortion(coeffs), width=width, height=height,
    )


def offline_calibration(
    socket: str, K: list[list[float]], width: int, height: int, dist: list[float] | None = None
) -> Any:
    """A ``CalibrationHandler`` for one sensor, as the EEPROM would hold it (tests, replays)."""
    calib = dai.CalibrationHandler()
    sock = board_socket(socket)
    calib.setCameraIntrinsics(sock, K, dai.Size2f(width, height))
    coeffs = list(dist or [])
    calib.setDistortionCoefficients(sock, coeffs + [0.0] * (14 - len(coeffs)))
    return calib
