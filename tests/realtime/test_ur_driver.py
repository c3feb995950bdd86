"""drivers.ur.adapter.URArm through the real ur_rtde client against the simulated controller."""

from __future__ import annotations

import math
import time

import numpy as np
import pytest

from drivers.arm import Arm
from drivers.errors import ConnectionLostError, MotionError, NotReadyError
from drivers.pose_history import PoseHistory
from drivers.ur.adapter import URArm
from drivers.ur.client_process import (
    QUIET_PUSH_S,
    RESTING_AFTER_S,
    ClientProcess,
    Create,
    Sample,
    StateSample,
    Subscribe,
)
from estimator.transforms import make_T, pose_distance, translation_T
from fakes.ur_controller.process import ControllerProcess, free_loopback_host
from tests.support.ur import true_T_base_tcp

pytestmark = pytest.mark.timeout(60)


def profile_time(distance: float, v: float, a: float) -> float:
    if distance >= v * v / a:
        return distance / v + v / a
    return 2.0 * math.sqrt(distance / a)


def assert_about(measured_s: float, expected_s: float) -> None:
    assert expected_s * 0.7 - 0.3 <= measured_s <= expected_s * 1.3 + 0.3, (
        f"took {measured_s:.3f} s, profile says {expected_s:.3f} s")


def test_satisfies_the_arm_protocol() -> None:
    assert isinstance(URArm("127.0.0.1"), Arm)


def test_unreachable_controller_is_a_clear_error_fast() -> None:
    host = free_loopback_host()  # nothing listens there
    t0 = time.monotonic()
    with pytest.raises(ConnectionLostError, match="unreachable"):
        URArm(host, connect_timeout_s=1.0).connect()
    assert time.monotonic() - t0 < 2.0


def test_not_in_remote_control_is_not_ready() -> None:
    with ControllerProcess(remote_control=False) as proc:
        ur_arm = URArm(proc.host)
        with pytest.raises(NotReadyError, match="remote"):
            ur_arm.connect()
        ur_arm.disconnect()


def test_power_on_then_moves_arrive_in_profile_time(ur_ctl: ControllerProcess) -> None:
    ur_arm = URArm(ur_ctl.host)
    ur_arm.connect()
    try:
        assert ur_arm.state().robot_mode == "POWER_OFF"
        with pytest.raises(NotReadyError):
            ur_arm.move_linear(ur_arm.tcp_pose(), 100, 500)
        ur_arm.power_on()
        state = ur_arm.state()
        assert state.ready and state.connected
        T0 = ur_arm.tcp_pose()
        assert pose_distance(T0, true_T_base_tcp(ur_ctl))[0] < 1e-6

        target = translation_T(60.0, -40.0, -100.0) @ T0
        t0 = time.monotonic()
        ur_arm.move_linear(target, 200.0, 1000.0)
        dist_m = math.dist(T0[:3, 3], target[:3, 3]) / 1000.0
        assert_about(time.monotonic() - t0, profile_time(dist_m, 0.2, 1.0))
        dt_mm, dr_deg = pose_distance(true_T_base_tcp(ur_ctl), target)
        assert dt_mm < 0.01 and dr_deg < 0.01

        q = ur_arm.joint_positions_rad()
        q_target = q + np.array([0.3, 0.0, 0.0, 0.0, 0.0, -0.5])
        t0 = time.monotonic()
        ur_arm.move_joint(q_target, 1.0, 2.0)
        assert_about(time.monotonic() - t0, profile_time(0.5, 1.0, 2.0))
        assert np.allclose(ur_ctl.state()["q"], q_target, atol=1e-6)
    finally:
        ur_arm.disconnect()


def test_async_move_and_pose_history(ur_ctl: ControllerProcess, ur_arm: URArm) -> None:
    T0 = ur_arm.tcp_pose()
    target = translation_T(0.0, 0.0, -150.0) @ T0
    t_start = time.monotonic()
    ur_arm.move_linear(target, 100.0, 500.0, wait=False)
    assert ur_arm.is_moving()
    assert ur_arm.async_progress() == 0
    t_mid = time.monotonic()
    time.sleep(0.3)
    mid = ur_arm.tcp_pose()
    assert 0.0 < T0[2, 3] - mid[2, 3] < 150.0  # under way, returned at once
    while ur_arm.is_moving():
        assert time.monotonic() - t_start < 5.0
        time.sleep(0.02)
    assert ur_arm.async_progress() == -1
    assert pose_distance(true_T_base_tcp(ur_ctl), target)[0] < 0.01
    # the history knows where the arm was: before, during and after the move
    assert pose_distance(ur_arm.pose_at(t_start - 0.01), T0)[0] < 0.5
    z_mid = ur_arm.pose_at(t_mid + 0.3)[2, 3]
    assert T0[2, 3] - 150.0 < z_mid < T0[2, 3]
    assert pose_distance(ur_arm.pose_at(time.monotonic()), target)[0] < 0.01
    with pytest.raises(LookupError):
        ur_arm.pose_at(time.monotonic() + 10.0)


def test_jog_stops_when_commands_stop(ur_ctl: ControllerProcess, ur_arm: URArm) -> None:
    T0 = ur_arm.tcp_pose()
    t0 = time.monotonic()
    for _ in range(10):  # 0.5 s of jogging at 20 mm/s along tool z
        ur_arm.jog(np.array([0.0, 0.0, 20.0, 0.0, 0.0, 0.0]), frame="tool", accel_mm_s2=500.0)
        time.sleep(0.05)
    t1 = time.monotonic()
    assert ur_arm.is_moving()
    time.sleep(ur_arm.watchdog_s + 0.5)  # watchdog expiry, then braking
    assert not ur_arm.is_moving()
    T1 = ur_arm.tcp_pose()
    time.sleep(0.3)
    assert pose_distance(ur_arm.tcp_pose(), T1)[0] < 1e-3  # it really stopped
    moved = T1[:3, 3] - T0[:3, 3]
    tool_z = T0[:3, 2]  # tool frame: the tool points down, so this is -z of the base
    along = float(moved @ tool_z)
    # jogged until the last command plus the watchdog period (and some braking), no longer
    jogged_s = t1 - t0
    assert 20.0 * jogged_s - 3.0 < along < 20.0 * (jogged_s + ur_arm.watchdog_s + 0.4) + 1.0, (
        f"moved {along:.1f} mm along tool z in {jogged_s:.2f} s of jogging")
    assert np.linalg.norm(moved - along * tool_z) < 0.5


def test_a_servo_twist_is_held_for_its_watchdog_time_then_braked(
        ur_ctl: ControllerProcess, ur_arm: URArm) -> None:
    """The servo law plans with holding a twist for ``watchdog_s`` before braking: the
    monitor wakes at that deadline (not on its next 20 ms check), so the arm's truth moves
    ``v * watchdog`` plus the braking distance after the last tick, and no more."""
    v_mm_s, accel, watchdog_s = 100.0, 2000.0, 0.05
    for _ in range(40):  # 0.32 s of 8 ms ticks: at speed
        time.sleep(0.008)
        ur_arm.servo_twist(np.array([v_mm_s, 0.0, 0.0, 0.0, 0.0, 0.0]), accel, watchdog_s)
    x_last = true_T_base_tcp(ur_ctl)[0, 3]
    time.sleep(0.5)
    assert not ur_arm.is_moving()
    travelled = true_T_base_tcp(ur_ctl)[0, 3] - x_last
    braking = v_mm_s ** 2 / (2.0 * accel)
    # generous for a loaded host: 30 ms late at most
    assert v_mm_s * watchdog_s * 0.5 < travelled < v_mm_s * (watchdog_s + 0.03) + braking, (
        f"{travelled:.2f} mm after the last tick")
    # a deadline 5 ms away: the monitor's next wake-up is that deadline, not its 20 ms check
    ur_arm._jog_deadline_s = time.monotonic() + 0.005
    assert ur_arm._monitor_wait_s() <= 0.006


def test_set_tcp_changes_the_reported_pose(ur_ctl: ControllerProcess, ur_arm: URArm) -> None:
    T_flange_tool0 = ur_arm.tcp_pose()
    T_flange_tcp = make_T(np.eye(3), [0.0, 0.0, 100.0])
    ur_arm.set_tcp(T_flange_tcp)
    time.sleep(0.05)
    expected = T_flange_tool0 @ T_flange_tcp
    assert pose_distance(ur_arm.tcp_pose(), expected)[0] < 1e-3
    assert np.allclose(ur_ctl.state()["tcp_offset"][:3], [0.0, 0.0, 0.1])


def test_bad_input_is_rejected_and_nothing_moves(ur_ctl: ControllerProcess, ur_arm: URArm) -> None:
    T0 = ur_arm.tcp_pose()
    with pytest.raises(MotionError):
        ur_arm.move_linear(np.eye(3), 100, 500)
    with pytest.raises(MotionError):
        ur_arm.move_linear(T0, -1.0, 500)
    with pytest.raises(MotionError):
        ur_arm.move_joint(np.array([0.0, 1.0]), 1.0, 1.0)
    with pytest.raises(MotionError):
        ur_arm.jog(np.array([np.nan] * 6))
    unreachable = translation_T(0.0, 0.0, 5000.0) @ T0
    with pytest.raises(MotionError, match="rejected"):
        ur_arm.move_linear(unreachable, 100, 500)
    assert pose_distance(true_T_base_tcp(ur_ctl), T0)[0] < 1e-6
    # the adapter restarts the control program: the next move works
    target = translation_T(0.0, 0.0, -20.0) @ T0
    ur_arm.move_linear(target, 100, 500)
    assert pose_distance(true_T_base_tcp(ur_ctl), target)[0] < 0.01


def test_reconnect_after_dropped_connections(ur_ctl: ControllerProcess, ur_arm: URArm) -> None:
    ur_ctl.drop_connections()
    deadline = time.monotonic() + 3.0
    with pytest.raises(ConnectionLostError):
        while time.monotonic() < deadline:
            ur_arm.tcp_pose()
            time.sleep(0.02)
    assert not ur_arm.state().connected
    ur_arm.reconnect()
    T0 = ur_arm.tcp_pose()
    target = translation_T(30.0, 0.0, 0.0) @ T0
    ur_arm.move_linear(target, 100, 500)
    assert pose_distance(true_T_base_tcp(ur_ctl), target)[0] < 0.01


def test_a_still_arms_frames_get_poses_from_samples_after_them(
        ur_ctl: ControllerProcess, ur_arm: URArm) -> None:
    """The child holds a standing arm's samples back; a frame's pose must still come from a
    sample taken after the frame (asked for, with the held one first), not the newest one
    pushed, which may be a tenth of a second older."""
    time.sleep(RESTING_AFTER_S + 2 * QUIET_PUSH_S)  # resting, samples held
    asked: list[float] = []
    ask = ur_arm._ask_sample

    def counted() -> StateSample:
        asked.append(time.monotonic())
        return ask()

    ur_arm._ask_sample = counted  # type: ignore[method-assign]
    truth = true_T_base_tcp(ur_ctl)
    for _ in range(10):
        exposed_s = time.monotonic() - 0.05  # a frame read 50 ms after its exposure
        T = ur_arm.pose_at(exposed_s)
        assert ur_arm.history.covers(exposed_s), "answered from samples before the frame"
        assert pose_distance(T, truth)[0] < 0.01
        time.sleep(0.033)
    assert asked, "a standing arm's frames waited for the quiet pushes"


def test_the_held_sample_comes_before_the_answer(ur_ctl: ControllerProcess) -> None:
    """What a Sample request makes the child send, in order: the still sample it held back,
    then the answer. The parent keeps samples in the order they were taken, so a held one that
    came after the answer would be dropped, and the history would not know the arm stood."""
    child = ClientProcess(ur_ctl.host)
    pushed: list[StateSample] = []
    child.on_push = pushed.append  # called by the reader, in pipe order, before any answer
    try:
        child.request(Create("recv"), timeout_s=15.0)
        child.request(Subscribe(0.008))
        time.sleep(RESTING_AFTER_S + 2 * QUIET_PUSH_S)
        answers: list[tuple[StateSample, int, int]] = []
        for _ in range(20):
            before = len(pushed)
            answer = child.request(Sample())
            answers.append((answer, before, len(pushed)))
            time.sleep(0.02)
        time.sleep(2 * QUIET_PUSH_S)
        flushed = 0
        for answer, before, after in answers:
            assert all(s.seq > answer.seq for s in pushed[after:]), "a held sample came late"
            flushed += any(s.seq < answer.seq for s in pushed[before:after])
        # the pusher holds a standing arm's newest sample most of the time; without the
        # flush a push lands in a request's millisecond only at the quiet period's tick
        assert flushed >= 5, f"{flushed} of 20 answers came after their held sample"
        assert [s.seq for s in pushed] == sorted(s.seq for s in pushed)
    finally:
        child.close()


def test_pose_history_interpolates() -> None:
    h = PoseHistory(4)
    A = np.eye(4)
    B = make_T(np.diag([1.0, -1.0, -1.0]), [10.0, 0.0, 0.0])  # 180 deg about x
    h.add(1.0, A)
    h.add(2.0, B)
    mid = h.at(1.5)
    assert np.allclose(mid[:3, 3], [5.0, 0.0, 0.0])
    assert pose_distance(mid, A)[1] == pytest.approx(90.0)
    assert np.allclose(h.at(2.01), B)  # just past the newest sample: the newest pose
    with pytest.raises(LookupError):
        h.at(0.5)
    for t in (3.0, 4.0, 5.0):
        h.add(t, B)
    with pytest.raises(LookupError):
        h.at(1.5)  # fell out of the ring buffer
