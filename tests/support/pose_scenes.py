"""Cameras and dot models shared by the pose-solver tests."""

from __future__ import annotations

import numpy as np

from estimator import CameraModel

CAM = CameraModel(800.0, 800.0, 640.0, 400.0)
CAM_DISTORTED = CameraModel(820.0, 810.0, 630.0, 410.0, dist=(-0.12, 0.05, 0.001, -0.0005, 0.0))
SOLID = np.array(
    [[0, 0, 0], [80, 0, 0], [0, 80, 0], [80, 80, 20], [40, -30, 60], [-30, 50, 40]], float
)
FLAT = np.array(
    [[0, 0, 0], [100, 0, 0], [0, 80, 0], [100, 80, 0], [50, 120, 0], [-30, 40, 0]], float
)
