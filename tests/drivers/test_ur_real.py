"""Opt-in checks against a real UR e-Series controller: ``pytest --ur-host IP``.

The robot must be in remote control with a clear workspace of at least 30 mm around the TCP:
the only motion is a 20 mm linear move down and back, and a short jog.
"""

from __future__ import annotations

import time
from collections.abc import Iterator

import numpy as np
import pytest

from drivers.ur.adapter import URArm
from estimator.transforms import pose_distance, translation_T

pytestmark = [pytest.mark.ur_hardware, pytest.mark.timeout(120)]


@pytest.fixture
def arm(ur_host: str) -> Iterator[URArm]:
    a = URArm(ur_host)
    a.connect()
    a.power_on()
    yield a
    a.disconnect()


def test_state_and_history(arm: URArm) -> None:
    state = arm.state()
    assert state.connected and state.ready
    assert state.joints_rad.shape == (6,)
    time.sleep(0.2)
    assert pose_distance(arm.pose_at(time.monotonic() - 0.1), arm.tcp_pose())[0] < 1.0


def test_small_move_and_back(arm: URArm) -> None:
    T0 = arm.tcp_pose()
    down = translation_T(0.0, 0.0, -20.0) @ T0
    arm.move_linear(down, 50.0, 250.0)
    assert pose_distance(arm.tcp_pose(), down)[0] < 0.5
    arm.move_linear(T0, 50.0, 250.0)
    assert pose_distance(arm.tcp_pose(), T0)[0] < 0.5


def test_jog_watchdog(arm: URArm) -> None:
    T0 = arm.tcp_pose()
    arm.jog(np.array([0.0, 0.0, 10.0, 0.0, 0.0, 0.0]), frame="base")
    time.sleep(arm.watchdog_s + 0.5)
    assert not arm.is_moving()
    moved = arm.tcp_pose()[2, 3] - T0[2, 3]
    assert 0.0 < moved < 10.0
    arm.move_linear(T0, 50.0, 250.0)
