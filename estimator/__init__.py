"""Pure vision and geometry: dot detection, correspondence, POSIT, refinement.

Imports nothing else of the project (numpy, SciPy and OpenCV only), so it can be reused and
tested on its own.

The names below are loaded on first use: a process that needs only the geometry
(``estimator.transforms``, e.g. the simulated controller) does not pay for OpenCV, numba and
the detection kernels at start.
"""

from __future__ import annotations

import importlib
import sys
import types
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from estimator.blobs import detect_blobs
    from estimator.camera import CameraModel
    from estimator.errors import (
        BehindCameraError,
        CorrespondenceError,
        DegenerateGeometryError,
        EstimationError,
        NotConvergedError,
        TooFewBlobsError,
    )
    from estimator.pipeline import Estimator
    from estimator.posit import PositResult
    from estimator.result import AlternativePose, Blob, PoseResult
    from estimator.seed import posit
    from estimator.solve import solve_pose
    from estimator.target import Target

_HOMES = {
    "AlternativePose": "estimator.result",
    "BehindCameraError": "estimator.errors",
    "Blob": "estimator.result",
    "CameraModel": "estimator.camera",
    "CorrespondenceError": "estimator.errors",
    "DegenerateGeometryError": "estimator.errors",
    "EstimationError": "estimator.errors",
    "Estimator": "estimator.pipeline",
    "NotConvergedError": "estimator.errors",
    "PoseResult": "estimator.result",
    "PositResult": "estimator.posit",
    "Target": "estimator.target",
    "TooFewBlobsError": "estimator.errors",
    "detect_blobs": "estimator.blobs",
    "posit": "estimator.seed",
    "solve_pose": "estimator.solve",
}

__all__ = [
    "AlternativePose",
    "BehindCameraError",
    "Blob",
    "CameraModel",
    "CorrespondenceError",
    "DegenerateGeometryError",
    "EstimationError",
    "Estimator",
    "NotConvergedError",
    "PoseResult",
    "PositResult",
    "Target",
    "TooFewBlobsError",
    "detect_blobs",
    "posit",
    "solve_pose",
]


def __getattr__(name: str) -> Any:
    home = _HOMES.get(name)
    if home is None:
        raise AttributeError(f"module 'estimator' has no attribute {name!r}")
    value = getattr(importlib.import_module(home), name)
    globals()[name] = value  # later lookups skip this function
    return value


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(_HOMES))


class _Package(types.ModuleType):
    """Keeps each public name its object: loading the submodule ``estimator.posit`` binds
    the module to the package's ``posit`` (the import system's rule), which would hide the
    function ``posit`` (from ``estimator.seed``) whenever that submodule loaded first. The
    submodule stays in ``sys.modules``."""

    def __setattr__(self, name: str, value: Any) -> None:
        if name in _HOMES and isinstance(value, types.ModuleType):
            return
        super().__setattr__(name, value)


sys.modules[__name__].__class__ = _Package
