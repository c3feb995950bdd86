"""Faults mid-move, through drivers.ur.URArm and the real ur_rtde client: safety stops,
a controller that dies or hangs, a stalled stream, a second control client."""

from __future__ import annotations

import threading
import time
from collections.abc import Iterator

import numpy as np
import pytest

from drivers.errors import (
    ConnectionLostError,
    EmergencyStopError,
    NotReadyError,
    ProtectiveStopError,
)
from drivers.ur import URArm
from estimator.transforms import T_from_ur_pose, pose_distance, translation_T
from fakes.ur_controller.process import ControllerProcess

pytestmark = pytest.mark.timeout(60)

HANG_BOUND_S = 3.0  # a dying controller must end a move in a typed error within this


@pytest.fixture
def ctl() -> Iterator[ControllerProcess]:
    with ControllerProcess() as proc:
        yield proc


@pytest.fixture
def arm(ctl: ControllerProcess) -> Iterator[URArm]:
    a = URArm(ctl.host)
    a.connect()
    a.power_on()
    yield a
    a.disconnect()


def sim_T(ctl: ControllerProcess) -> np.ndarray:
    return T_from_ur_pose(ctl.state()["tcp_pose"])


def test_protective_stop_mid_move_refuses_motion_until_recovered(
        ctl: ControllerProcess, arm: URArm) -> None:
    T0 = arm.tcp_pose()
    target = translation_T(0.0, 0.0, -200.0) @ T0  # 2 s at 100 mm/s
    ctl.protective_stop(after_s=0.5)
    with pytest.raises(ProtectiveStopError):
        arm.move_linear(target, 100.0, 500.0)
    state = arm.state()
    assert state.protective_stop and not state.ready
    time.sleep(0.3)
    stopped = sim_T(ctl)
    assert 10.0 < T0[2, 3] - stopped[2, 3] < 150.0  # stopped part way
    with pytest.raises(ProtectiveStopError):
        arm.move_linear(T0, 100.0, 500.0)
    with pytest.raises(ProtectiveStopError):
        arm.jog(np.array([10.0, 0, 0, 0, 0, 0]))
    with pytest.raises(NotReadyError, match="5s"):
        arm.recover_protective_stop()  # the controller refuses within 5 s of the stop
    assert pose_distance(sim_T(ctl), stopped)[0] < 1e-6  # nothing moved meanwhile
    time.sleep(5.2)
    arm.recover_protective_stop()
    assert arm.state().ready
    arm.move_linear(target, 200.0, 1000.0)
    assert pose_distance(sim_T(ctl), target)[0] < 0.01


def test_emergency_stop_mid_move(ctl: ControllerProcess, arm: URArm) -> None:
    T0 = arm.tcp_pose()
    ctl.emergency_stop(after_s=0.4)
    with pytest.raises(EmergencyStopError):
        arm.move_linear(translation_T(0.0, 0.0, -200.0) @ T0, 100.0, 500.0)
    time.sleep(0.3)
    assert arm.state().emergency_stop
    with pytest.raises(EmergencyStopError):
        arm.power_on()
    ctl.release_emergency_stop()
    time.sleep(0.1)
    arm.power_on()
    arm.move_linear(T0, 100.0, 500.0)
    assert pose_distance(sim_T(ctl), T0)[0] < 0.01


@pytest.mark.parametrize("fault", ["kill", "freeze"])
def test_controller_dying_mid_move_is_a_typed_error_not_a_hang(
        ctl: ControllerProcess, arm: URArm, fault: str) -> None:
    T0 = arm.tcp_pose()
    target = translation_T(0.0, 0.0, -200.0) @ T0  # 4 s at 50 mm/s
    died_at: list[float] = []

    def die() -> None:
        died_at.append(time.monotonic())
        ctl.kill() if fault == "kill" else ctl.freeze()

    threading.Timer(0.5, die).start()
    with pytest.raises(ConnectionLostError):
        arm.move_linear(target, 50.0, 500.0)
    took = time.monotonic() - died_at[0]
    assert took < HANG_BOUND_S, f"{fault}: the error came {took:.2f} s after the fault"
    assert not arm.state().connected
    for call in (arm.tcp_pose, arm.is_moving, arm.stop):
        with pytest.raises(ConnectionLostError):
            call()
    t0 = time.monotonic()
    with pytest.raises(ConnectionLostError):
        arm.reconnect()  # nothing answers any more
    assert time.monotonic() - t0 < HANG_BOUND_S


def test_stalled_stream_then_reconnect(ctl: ControllerProcess, arm: URArm) -> None:
    ctl.stall_stream(1.5)
    t0 = time.monotonic()
    with pytest.raises(ConnectionLostError, match="no RTDE data"):
        while time.monotonic() - t0 < 3.0:
            arm.is_moving()
            time.sleep(0.02)
    assert time.monotonic() - t0 < 1.5
    time.sleep(max(0.0, 1.6 - (time.monotonic() - t0)))
    arm.reconnect()
    T0 = arm.tcp_pose()
    target = translation_T(0.0, 25.0, 0.0) @ T0
    arm.move_linear(target, 100.0, 500.0)
    assert pose_distance(sim_T(ctl), target)[0] < 0.01


def test_second_controlling_adapter_is_refused(ctl: ControllerProcess, arm: URArm) -> None:
    other = URArm(ctl.host, connect_timeout_s=1.0)
    try:
        with pytest.raises(NotReadyError, match="in use"):
            other.connect()  # the arm is RUNNING, so connect() takes control: refused
    finally:
        other.disconnect()
    arm.move_linear(translation_T(0.0, 0.0, -10.0) @ arm.tcp_pose(), 100.0, 500.0)
