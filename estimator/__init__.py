"""Pure vision and geometry: dot detection, correspondence, POSIT, refinement.

Imports nothing else of the project (numpy, SciPy and OpenCV only), so it can be reused and
tested on its own.
"""

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
