"""SimArm: the in-process simulated UR5e behind drivers.arm.Arm (mm, 4x4, driver errors)."""

from __future__ import annotations

import time
from collections.abc import Iterator

import numpy as np
import pytest

from drivers.arm import Arm
from drivers.errors import (
    ConnectionLostError,
    EmergencyStopError,
    MotionError,
    NotReadyError,
    ProtectiveStopError,
    UnlockTooEarlyError,
)
from estimator.transforms import T_from_pose, pose_distance, translation_T
from fakes.sim_arm import SimArm
from fakes.ur_sim import SimLimits

FAST = SimLimits(power_on_s=0.05, brake_release_s=0.05, unlock_delay_s=0.5)


@pytest.fixture
def arm() -> Iterator[SimArm]:
    a = SimArm(limits=FAST, jog_watchdog_s=0.15)
    a.connect()
    a.power_on()
    yield a
    a.close()


def _wait_still(arm: SimArm, timeout_s: float = 3.0) -> None:
    deadline = time.monotonic() + timeout_s
    while arm.is_moving() and time.monotonic() < deadline:
        time.sleep(0.01)


def test_satisfies_the_arm_protocol() -> None:
    a = SimArm(limits=FAST)
    try:
        assert isinstance(a, Arm)
    finally:
        a.close()


def test_needs_connect_and_power() -> None:
    a = SimArm(limits=FAST)
    try:
        with pytest.raises(ConnectionLostError):
            a.tcp_pose()
        a.connect()
        st = a.state()
        assert st.connected and st.robot_mode == "POWER_OFF" and not st.ready
        with pytest.raises(NotReadyError):
            a.move_joint(st.joints_rad, 0.5, 1.0)
        a.power_on()
        assert a.state().ready
    finally:
        a.close()
    with pytest.raises(ConnectionLostError):
        a.connect()  # the controller is gone


def test_move_linear_and_joint_in_mm(arm: SimArm) -> None:
    T0 = arm.tcp_pose()
    assert T0.shape == (4, 4) and T0[2, 3] > 400.0  # mm
    T1 = translation_T(50.0, -30.0, -80.0) @ T0
    t0 = time.monotonic()
    arm.move_linear(T1, 200.0, 1000.0)
    assert time.monotonic() - t0 > 0.4  # 100 mm at 200 mm/s takes real time
    dt_mm, dr_deg = pose_distance(arm.tcp_pose(), T1)
    assert dt_mm < 1e-3 and dr_deg < 1e-4
    assert not arm.is_moving()
    q = arm.joint_positions_rad() + np.array([0.2, 0.0, 0.0, 0.0, 0.0, -0.3])
    arm.move_joint(q, 1.0, 2.0)
    assert np.allclose(arm.joint_positions_rad(), q, atol=1e-6)
    # non-blocking
    arm.move_linear(T0, 200.0, 1000.0, wait=False)
    assert arm.is_moving()
    _wait_still(arm)
    assert pose_distance(arm.tcp_pose(), T0)[0] < 1e-3


def test_tcp_changes_the_reported_pose(arm: SimArm) -> None:
    T_before = arm.tcp_pose()
    T_flange_tcp = T_from_pose([0.0, 0.0, 150.0], [0.0, 0.0, 0.0])
    arm.set_tcp(T_flange_tcp)
    T_after = arm.tcp_pose()
    assert np.allclose(T_after, T_before @ T_flange_tcp, atol=1e-9)


def test_unreachable_move_is_a_motion_error(arm: SimArm) -> None:
    q0 = arm.joint_positions_rad()
    with pytest.raises(MotionError):
        arm.move_linear(translation_T(2000.0, 0.0, 0.0) @ arm.tcp_pose(), 100.0, 500.0)
    with pytest.raises(MotionError):
        arm.move_joint(q0 + 10.0, 0.5, 1.0)
    assert np.array_equal(arm.joint_positions_rad(), q0)


def test_jog_stops_when_not_resent(arm: SimArm) -> None:
    T0 = arm.tcp_pose()
    for _ in range(5):
        arm.jog(np.array([40.0, 0.0, 0.0, 0.0, 0.0, 0.0]), "base", 400.0)
        time.sleep(0.05)
    assert arm.is_moving()
    t_last = time.monotonic()
    _wait_still(arm, 2.0)
    assert not arm.is_moving()
    assert time.monotonic() - t_last < 1.0  # watchdog 0.15 s + braking
    d = arm.tcp_pose()[:3, 3] - T0[:3, 3]
    assert d[0] > 5.0 and abs(d[1]) < 1e-3 and abs(d[2]) < 1e-3


def test_stop_is_always_accepted(arm: SimArm) -> None:
    arm.stop()
    T0 = arm.tcp_pose()
    arm.move_linear(translation_T(0.0, 0.0, -150.0) @ T0, 100.0, 500.0, wait=False)
    time.sleep(0.5)
    arm.stop(2000.0)
    _wait_still(arm, 1.0)
    z = arm.tcp_pose()[2, 3]
    assert T0[2, 3] - 150.0 + 1.0 < z < T0[2, 3] - 10.0


def test_protective_stop_mid_move_then_recover(arm: SimArm) -> None:
    T0 = arm.tcp_pose()
    arm.engine.inject("protective_stop", after_s=0.4)
    with pytest.raises(ProtectiveStopError):
        arm.move_linear(translation_T(0.0, 150.0, 0.0) @ T0, 100.0, 500.0)
    st = arm.state()
    assert st.protective_stop and not st.ready and not st.moving
    with pytest.raises(ProtectiveStopError):
        arm.move_linear(T0, 100.0, 500.0)
    with pytest.raises(UnlockTooEarlyError) as refused:
        arm.recover_protective_stop()  # refused right after the stop
    assert 0.0 < refused.value.retry_in_s <= arm.engine.limits.unlock_delay_s
    time.sleep(0.6)
    arm.recover_protective_stop()
    assert arm.state().ready
    arm.move_linear(T0, 100.0, 500.0)
    assert pose_distance(arm.tcp_pose(), T0)[0] < 1e-3


def test_emergency_stop_reports(arm: SimArm) -> None:
    T0 = arm.tcp_pose()
    arm.engine.inject("emergency_stop", after_s=0.3)
    with pytest.raises(EmergencyStopError):
        arm.move_linear(translation_T(0.0, 100.0, 0.0) @ T0, 100.0, 500.0)
    assert arm.state().emergency_stop
    with pytest.raises(EmergencyStopError):
        arm.recover_protective_stop()


def test_pose_history(arm: SimArm) -> None:
    T0 = arm.tcp_pose()
    arm.move_linear(translation_T(0.0, 0.0, -100.0) @ T0, 150.0, 1000.0, wait=False)
    samples = []
    while arm.is_moving():
        st = arm.state()
        samples.append((st.timestamp_s, st.T_base_tcp))
        time.sleep(0.03)
    assert len(samples) > 5
    for t, T in samples:
        assert pose_distance(arm.pose_at(t), T)[0] < 0.5  # mm
    assert pose_distance(arm.pose_at(time.monotonic()), arm.tcp_pose())[0] < 1e-6
    with pytest.raises(LookupError):
        arm.pose_at(time.monotonic() + 5.0)
    with pytest.raises(LookupError):
        arm.pose_at(time.monotonic() - 3600.0)
