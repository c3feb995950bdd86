"""Helpers for tests that drive the simulated UR controller through the real UR adapter."""

from __future__ import annotations

import numpy as np

from estimator.transforms import T_from_ur_pose
from fakes.ur_controller.process import ControllerProcess


def true_T_base_tcp(ctl: ControllerProcess) -> np.ndarray:
    """Ground truth: the simulated arm's TCP pose, read from the controller process."""
    return T_from_ur_pose(ctl.state()["tcp_pose"])

