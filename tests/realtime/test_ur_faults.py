"""Faults mid-move, through drivers.ur.adapter.URArm and the real ur_rtde client: safety stops,
a controller that dies or hangs, a stalled stream, a second control client."""

from __future__ import annotations

import threading
import time

import numpy as np
import pytest

from drivers.errors import (
    ConnectionLostError,
    EmergencyStopError,
    NotReadyError,
    ProtectiveStopError,
)
from drivers.ur.adapter import URArm
from estimator.transforms import pose_distance, translation_T
from fakes.ur_controller.process import ControllerProcess
from tests.support.ur import true_T_base_tcp

pytestmark = pytest.mark.timeout(60)

HANG_BOUND_S = 3.0  # a dying controller must end a move in a typed error within this


def test_protective_stop_mid_move_refuses_motion_until_recovered(
        ur_ctl: ControllerProcess, ur_arm: URArm) -> None:
    T0 = ur_arm.tcp_pose()
    target = translation_T(0.0, 0.0, -200.0) @ T0  # 2 s at 100 mm/s
    ur_ctl.protective_stop(after_s=0.5)
    with pytest.raises(ProtectiveStopError):
        ur_arm.move_linear(target, 100.0, 500.0)
    state = ur_arm.state()
    assert state.protective_stop and not state.ready
    time.sleep(0.3)
    stopped = true_T_base_tcp(ur_ctl)
    assert 10.0 < T0[2, 3] - stopped[2, 3] < 150.0  # stopped part way
    with pytest.raises(ProtectiveStopError):
        ur_arm.move_linear(T0, 100.0, 500.0)
    with pytest.raises(ProtectiveStopError):
        ur_arm.jog(np.array([10.0, 0, 0, 0, 0, 0]))
    with pytest.raises(NotReadyError, match="5s"):
        ur_arm.recover_protective_stop()  # the controller refuses within 5 s of the stop
    assert pose_distance(true_T_base_tcp(ur_ctl), stopped)[0] < 1e-6  # nothing moved meanwhile
    time.sleep(5.2)
    ur_arm.recover_protective_stop()
    assert ur_arm.state().ready
    ur_arm.move_linear(target, 200.0, 1000.0)
    assert pose_distance(true_T_base_tcp(ur_ctl), target)[0] < 0.01


def test_emergency_stop_mid_move(ur_ctl: ControllerProcess, ur_arm: URArm) -> None:
    T0 = ur_arm.tcp_pose()
    ur_ctl.emergency_stop(after_s=0.4)
    with pytest.raises(EmergencyStopError):
        ur_arm.move_linear(translation_T(0.0, 0.0, -200.0) @ T0, 100.0, 500.0)
    time.sleep(0.3)
    assert ur_arm.state().emergency_stop
    with pytest.raises(EmergencyStopError):
        ur_arm.power_on()
    ur_ctl.release_emergency_stop()
    time.sleep(0.1)
    ur_arm.power_on()
    ur_arm.move_linear(T0, 100.0, 500.0)
    assert pose_distance(true_T_base_tcp(ur_ctl), T0)[0] < 0.01


@pytest.mark.parametrize("fault", ["kill", "freeze"])
def test_controller_dying_mid_move_is_a_typed_error_not_a_hang(
        ur_ctl: ControllerProcess, ur_arm: URArm, fault: str) -> None:
    T0 = ur_arm.tcp_pose()
    target = translation_T(0.0, 0.0, -200.0) @ T0  # 4 s at 50 mm/s
    died_at: list[float] = []

    def die() -> None:
        died_at.append(time.monotonic())
        ur_ctl.kill() if fault == "kill" else ur_ctl.freeze()

    threading.Timer(0.5, die).start()
    with pytest.raises(ConnectionLostError):
        ur_arm.move_linear(target, 50.0, 500.0)
    took = time.monotonic() - died_at[0]
    assert took < HANG_BOUND_S, f"{fault}: the error came {took:.2f} s after the fault"
    assert not ur_arm.state().connected
    for call in (ur_arm.tcp_pose, ur_arm.is_moving, ur_arm.stop):
        with pytest.raises(ConnectionLostError):
            call()
    t0 = time.monotonic()
    with pytest.raises(ConnectionLostError):
        ur_arm.reconnect()  # nothing answers any more
    assert time.monotonic() - t0 < HANG_BOUND_S


def test_stalled_stream_then_reconnect(ur_ctl: ControllerProcess, ur_arm: URArm) -> None:
    assert ur_arm.stale_after_s == 1.5  # the default: a loaded cell PC must not trip it
    fresh = ur_arm.state()
    assert 0.0 <= time.monotonic() - fresh.timestamp_s < 0.5  # when the pose was taken
    ur_ctl.stall_stream(2.5)
    t0 = time.monotonic()
    time.sleep(0.6)
    # until the link is declared lost, the state says how old its pose is (the guard's
    # max_pose_age_s and a servo loop's extrapolation go by it), not when it was asked for
    assert time.monotonic() - ur_arm.state().timestamp_s > 0.5
    with pytest.raises(ConnectionLostError, match="no RTDE data"):
        while time.monotonic() - t0 < 4.0:
            ur_arm.is_moving()
            time.sleep(0.02)
    assert time.monotonic() - t0 < 2.5
    time.sleep(max(0.0, 2.6 - (time.monotonic() - t0)))
    ur_arm.reconnect()
    T0 = ur_arm.tcp_pose()
    target = translation_T(0.0, 25.0, 0.0) @ T0
    ur_arm.move_linear(target, 100.0, 500.0)
    assert pose_distance(true_T_base_tcp(ur_ctl), target)[0] < 0.01


def test_second_controlling_adapter_is_refused(ur_ctl: ControllerProcess, ur_arm: URArm) -> None:
    other = URArm(ur_ctl.host, connect_timeout_s=1.0)
    try:
        with pytest.raises(NotReadyError, match="in use"):
            other.connect()  # the arm is RUNNING, so connect() takes control: refused
    finally:
        other.disconnect()
    ur_arm.move_linear(translation_T(0.0, 0.0, -10.0) @ ur_arm.tcp_pose(), 100.0, 500.0)
