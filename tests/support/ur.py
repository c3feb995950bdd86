"""Helpers for tests that drive the simulated UR controller through the real UR adapter."""

from __future__ import annotations

import time
from collections.abc import Callable

import numpy as np

from estimator.transforms import T_from_ur_pose
from fakes.ur_controller.process import ControllerProcess


def true_T_base_tcp(ctl: ControllerProcess) -> np.ndarray:
    """Ground truth: the simulated arm's TCP pose, read from the controller process."""
    return T_from_ur_pose(ctl.state()["tcp_pose"])


def wait_until(pred: Callable[[], bool], timeout_s: float = 3.0, poll_s: float = 0.005) -> bool:
    """Poll ``pred`` until it holds or ``timeout_s`` passes: on a loaded host the receive
    stream may be some packages behind the control one."""
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if pred():
            return True
        time.sleep(poll_s)
    return pred()
