"""Pure vision and geometry: dot detection, correspondence, POSIT, refinement.

Imports nothing else of the project (numpy, SciPy and OpenCV only), so it can be reused and
tested on its own.
"""

from estimator.camera import CameraModel
from estimator.errors import (
    BehindCameraError,
    CorrespondenceError,
    DegenerateGeometryError,
    EstimationError,
    NotConvergedError,
    TooFewBlobsError,
)
from estimator.result import AlternativePose, Blob, PoseResult
from estimator.target import Target

__all__ = [
    "AlternativePose",
    "BehindCameraError",
    "Blob",
    "CameraModel",
    "CorrespondenceError",
    "DegenerateGeometryError",
    "EstimationError",
    "NotConvergedError",
    "PoseResult",
    "Target",
    "TooFewBlobsError",
]
# posit, solve_pose, detect_blobs and Estimator are added here as their modules land.
