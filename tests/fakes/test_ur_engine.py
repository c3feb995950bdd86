"""The simulated UR controller's motion engine, in real time.

Timing assertions are loose (profile time +-30 % / +0.3 s) because the suite shares 2 cores with
other test runs; positions are exact because profiles land on their targets.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Iterator

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from fakes.ur_sim.engine import (
    CYCLE_S,
    HOME_Q_RAD,
    CommandOutcome,
    CommandRejectedError,
    EmergencyStopActiveError,
    EngineSnapshot,
    MotionEngine,
    NotRunningError,
    ProtectiveStopActiveError,
    RobotMode,
    RobotStatusBit,
    SafetyMode,
    SafetyPlane,
    SafetyStatusBit,
    SimLimits,
    UnreachablePoseError,
)
from fakes.ur_sim.kinematics import UR5eKinematics
from fakes.ur_sim.profiles import JointProfile, LinearProfile

FAST = SimLimits(power_on_s=0.05, brake_release_s=0.05, unlock_delay_s=0.5)


def _wait(e: MotionEngine, pred: Callable[[EngineSnapshot], bool], timeout_s: float = 5.0
          ) -> EngineSnapshot:
    deadline = time.monotonic() + timeout_s
    while True:
        s = e.snapshot()
        if pred(s) or time.monotonic() > deadline:
            return s
        time.sleep(0.005)


def _running(limits: SimLimits = FAST) -> MotionEngine:
    e = MotionEngine(limits=limits)
    e.brake_release()
    assert _wait(e, lambda s: s.robot_mode == RobotMode.RUNNING).robot_mode == RobotMode.RUNNING
    return e


@pytest.fixture
def eng() -> Iterator[MotionEngine]:
    e = _running()
    yield e
    e.close()


def _plus(q: object, delta: list[float]) -> np.ndarray:
    return np.asarray(q, dtype=float) + np.asarray(delta, dtype=float)


def _about(measured: float, expected: float) -> bool:
    return 0.7 * expected <= measured <= 1.3 * expected + 0.3


def test_start_state_and_power_sequence() -> None:
    with MotionEngine(limits=SimLimits(power_on_s=0.2, brake_release_s=0.2)) as e:
        s = e.snapshot()
        assert s.robot_mode == RobotMode.POWER_OFF and s.safety_mode == SafetyMode.NORMAL
        assert s.q == HOME_Q_RAD and not s.moving and s.async_progress == -1
        assert s.safety_status_bits == 1 << SafetyStatusBit.NORMAL_MODE
        assert s.robot_status_bits == 0
        assert s.tcp_pose[2] > 0.4  # tool above the table, pointing down
        with pytest.raises(NotRunningError):
            e.move_j(list(HOME_Q_RAD), 1.0, 1.0)
        e.brake_release()
        seen = {_wait(e, lambda s: s.robot_mode != RobotMode.POWER_OFF, 1).robot_mode}
        seen.add(_wait(e, lambda s: s.robot_mode == RobotMode.IDLE, 1).robot_mode)
        s = _wait(e, lambda s: s.robot_mode == RobotMode.RUNNING, 2)
        assert seen == {RobotMode.POWER_ON, RobotMode.IDLE}
        assert s.robot_mode == RobotMode.RUNNING
        assert s.robot_status_bits & (1 << RobotStatusBit.POWER_ON)
        assert s.timestamp_s > 0.3
        e.power_off()
        assert e.snapshot().robot_mode == RobotMode.POWER_OFF


def test_move_j_reaches_target_in_profile_time(eng: MotionEngine) -> None:
    q0 = np.array(eng.snapshot().q)
    q1 = q0 + np.array([0.6, 0.2, -0.3, 0.1, 0.2, -0.4])
    expected = JointProfile(q0, q1, 1.0, 2.0).duration_s
    t0 = time.monotonic()
    cid = eng.move_j(q1.tolist(), 1.0, 2.0)
    mid = _wait(eng, lambda s: time.monotonic() - t0 > expected / 2)
    assert mid.moving and mid.active_command == "movej" and mid.async_progress == 0
    assert 0.3 < max(abs(v) for v in mid.qd) <= 1.0 + 1e-9
    assert eng.wait_until_idle(10)
    elapsed = time.monotonic() - t0
    s = eng.snapshot()
    assert _about(elapsed, expected), (elapsed, expected)
    assert np.allclose(s.q, q1, atol=1e-6)
    assert not s.moving and s.async_progress == -1
    assert eng.outcome(cid) == CommandOutcome.SUCCEEDED
    assert np.allclose(s.tcp_pose, eng.fk(q1.tolist()), atol=1e-9)


def test_move_l_straight_line_in_profile_time(eng: MotionEngine) -> None:
    kin = UR5eKinematics()
    start = eng.snapshot()
    p0 = np.array(start.tcp_pose)
    p1 = p0 + np.array([0.12, 0.08, -0.15, 0.0, 0.0, 0.0])
    p1[3:] = (kin.forward(start.q)[:3, :3] @ np.eye(3))[0] * 0 + p0[3:]  # same orientation
    from estimator.transforms import T_from_ur_pose

    expected = LinearProfile(T_from_ur_pose(p0), T_from_ur_pose(p1), 250.0, 1000.0,
                             0.25, 1.0).duration_s
    t0 = time.monotonic()
    eng.move_l(p1.tolist(), 0.25, 1.0)
    line = (p1 - p0)[:3] / np.linalg.norm((p1 - p0)[:3])
    worst = 0.0
    speeds = []
    while eng.snapshot().moving:
        s = eng.snapshot()
        off = np.array(s.tcp_pose[:3]) - p0[:3]
        worst = max(worst, float(np.linalg.norm(off - (off @ line) * line)))
        speeds.append(float(np.linalg.norm(s.tcp_speed[:3])))
        time.sleep(0.01)
    elapsed = time.monotonic() - t0
    s = eng.snapshot()
    assert _about(elapsed, expected), (elapsed, expected)
    assert np.allclose(s.tcp_pose, p1, atol=1e-6)
    assert worst < 1e-6  # on the straight line, to numerical precision
    assert 0.2 < max(speeds) <= 0.25 * 1.02


def test_move_j_ik_goes_to_pose(eng: MotionEngine) -> None:
    p = list(eng.snapshot().tcp_pose)
    p[1] += 0.1
    eng.move_j_ik(p, 1.0, 2.0)
    assert eng.wait_until_idle(10)
    assert np.allclose(eng.snapshot().tcp_pose, p, atol=1e-6)


def test_invalid_commands_change_nothing(eng: MotionEngine) -> None:
    before = eng.snapshot()
    q = list(before.q)
    bad_q = q.copy()
    bad_q[0] = 7.0  # beyond +2 pi
    far = list(before.tcp_pose)
    far[0] = 2.0
    attempts: list[Callable[[], object]] = [
        lambda: eng.move_j(bad_q, 1.0, 1.0),
        lambda: eng.move_j(q[:5], 1.0, 1.0),
        lambda: eng.move_j([math.nan] * 6, 1.0, 1.0),
        lambda: eng.move_j(q, -1.0, 1.0),
        lambda: eng.move_j(q, 10.0, 1.0),  # above the joint speed maximum
        lambda: eng.move_l(far, 0.1, 1.0),
        lambda: eng.move_path([("movej", q, 1.0, 1.0, 0.0), ("movej", bad_q, 1.0, 1.0, 0.0)]),
        lambda: eng.move_path([("movez", q, 1.0, 1.0, 0.0)]),  # type: ignore[list-item]
        lambda: eng.servo_j(q, 0.002, 0.5, 300.0),
        lambda: eng.set_speed_fraction(1.5),
    ]
    for attempt in attempts:
        with pytest.raises(CommandRejectedError):
            attempt()
    with pytest.raises(UnreachablePoseError):
        eng.move_l(far, 0.1, 1.0)
    time.sleep(0.05)
    after = eng.snapshot()
    assert after.q == before.q and not after.moving
    assert after.safety_mode == SafetyMode.NORMAL
    assert after.last_command_id == before.last_command_id


def test_workspace_exit_trips_protective_stop() -> None:
    e = _running(SimLimits(power_on_s=0.05, brake_release_s=0.05, unlock_delay_s=0.5,
                           safety_planes=(SafetyPlane.floor(0.35),)))
    try:
        p = list(e.snapshot().tcp_pose)
        target = p.copy()
        target[2] = 0.2  # below the floor of the workspace
        cid = e.move_l(target, 0.2, 1.0)
        s = _wait(e, lambda s: s.safety_mode == SafetyMode.PROTECTIVE_STOP)
        assert s.safety_mode == SafetyMode.PROTECTIVE_STOP
        assert "safety plane" in s.last_stop_reason
        assert e.wait_until_idle(2)
        s = e.snapshot()
        # stopped at the boundary: the crossing cycle is refused, then a short braking distance
        assert 0.33 < s.tcp_pose[2] <= 0.38
        assert e.outcome(cid) == CommandOutcome.ABORTED
        assert s.safety_status_bits & (1 << SafetyStatusBit.PROTECTIVE_STOPPED)
        assert s.speed_scaling == 0.0
        with pytest.raises(ProtectiveStopActiveError):
            e.move_j(list(s.q), 0.5, 1.0)
        assert not e.unlock_protective_stop()  # refused within the unlock delay
        time.sleep(0.6)
        assert e.unlock_protective_stop()
        up = list(e.snapshot().tcp_pose)
        up[2] += 0.05  # moving back inside is allowed
        e.move_l(up, 0.1, 1.0)
        assert e.wait_until_idle(5)
        assert e.snapshot().safety_mode == SafetyMode.NORMAL
    finally:
        e.close()


def test_tool_speed_limit_trips_protective_stop(eng: MotionEngine) -> None:
    p = list(eng.snapshot().tcp_pose)
    p[0] += 0.1
    with pytest.raises(ProtectiveStopActiveError):
        eng.move_l(p, 2.0, 1.0)  # above the 1.5 m/s tool speed limit
    assert eng.snapshot().safety_mode == SafetyMode.PROTECTIVE_STOP
    time.sleep(0.6)
    assert eng.unlock_protective_stop()
    with pytest.raises(ProtectiveStopActiveError):
        eng.speed_l([0.0, 0.0, 2.0, 0, 0, 0], 1.0)
    assert eng.snapshot().q == tuple(HOME_Q_RAD)


def test_fast_joint_move_exceeding_tool_speed_stops_mid_move(eng: MotionEngine) -> None:
    # Arm stretched out horizontally swinging about the base at 3.1 rad/s: the TCP would
    # exceed 1.5 m/s.
    q = [0.0, 0.0, 0.0, -1.571, 0.0, 0.0]
    eng.move_j(q, 1.0, 4.0)
    assert eng.wait_until_idle(10)
    q2 = q.copy()
    q2[0] = 3.0
    cid = eng.move_j(q2, 3.1, 20.0)
    assert eng.wait_until_idle(10)
    s = eng.snapshot()
    assert eng.outcome(cid) == CommandOutcome.ABORTED
    assert s.safety_mode == SafetyMode.PROTECTIVE_STOP and "tool speed" in s.last_stop_reason
    assert 0.0 < s.q[0] < 2.0


def test_unlock_refused_for_five_seconds_like_a_real_controller() -> None:
    e = _running(SimLimits(power_on_s=0.05, brake_release_s=0.05))
    try:
        assert e.limits.unlock_delay_s == 5.0
        e.trigger_protective_stop("test")
        t0 = time.monotonic()
        assert not e.unlock_protective_stop()
        time.sleep(4.0)
        assert not e.unlock_protective_stop()
        s = e.snapshot()
        assert s.seconds_since_protective_stop is not None
        assert s.seconds_since_protective_stop >= 4.0
        time.sleep(max(0.0, 5.05 - (time.monotonic() - t0)))
        assert e.unlock_protective_stop()
        assert e.snapshot().safety_mode == SafetyMode.NORMAL
    finally:
        e.close()


def test_protective_stop_mid_move_aborts_and_blocks(eng: MotionEngine) -> None:
    q0 = np.array(eng.snapshot().q)
    q1 = q0 + np.array([1.0, 0, 0, 0, 0, 0])
    cid = eng.move_j(q1.tolist(), 0.5, 1.0)  # about 2.5 s
    eng.inject("protective_stop", after_s=0.8)
    s = _wait(eng, lambda s: s.safety_mode == SafetyMode.PROTECTIVE_STOP, 5)
    assert s.safety_mode == SafetyMode.PROTECTIVE_STOP
    assert eng.wait_until_idle(1.0)
    s = eng.snapshot()
    assert eng.outcome(cid) == CommandOutcome.ABORTED
    assert not s.moving and not any(s.qd)
    assert q0[0] + 0.1 < s.q[0] < q1[0] - 0.3
    with pytest.raises(ProtectiveStopActiveError):
        eng.move_j(q1.tolist(), 0.5, 1.0)
    with pytest.raises(ProtectiveStopActiveError):
        eng.speed_j([0.1, 0, 0, 0, 0, 0], 1.0)
    time.sleep(0.6)
    assert eng.unlock_protective_stop()
    eng.move_j(q1.tolist(), 1.0, 2.0)
    assert eng.wait_until_idle(5)
    assert np.allclose(eng.snapshot().q, q1, atol=1e-6)


def test_emergency_stop_powers_off_until_released(eng: MotionEngine) -> None:
    q1 = np.array(HOME_Q_RAD) + np.array([0.8, 0, 0, 0, 0, 0])
    cid = eng.move_j(q1.tolist(), 0.5, 1.0)
    eng.inject("emergency_stop", after_s=0.5)
    s = _wait(eng, lambda s: s.robot_mode == RobotMode.POWER_OFF, 5)
    assert s.robot_mode == RobotMode.POWER_OFF
    assert s.safety_mode == SafetyMode.ROBOT_EMERGENCY_STOP
    assert s.safety_status_bits & (1 << SafetyStatusBit.EMERGENCY_STOPPED)
    assert eng.outcome(cid) == CommandOutcome.ABORTED and not s.moving
    with pytest.raises(EmergencyStopActiveError):
        eng.move_j(q1.tolist(), 0.5, 1.0)
    with pytest.raises(EmergencyStopActiveError):
        eng.power_on()
    eng.release_emergency_stop()
    assert eng.snapshot().safety_mode == SafetyMode.NORMAL
    eng.brake_release()
    assert _wait(eng, lambda s: s.robot_mode == RobotMode.RUNNING).robot_mode == RobotMode.RUNNING


def test_servo_stream_tracks_and_brakes_when_stream_stops(eng: MotionEngine) -> None:
    q0 = np.array(eng.snapshot().q)
    t0 = time.monotonic()
    target = q0
    while (t := time.monotonic() - t0) < 0.6:
        target = q0 + np.array([0.3 * math.sin(2 * t), 0, 0.2 * t, 0, 0, 0])
        eng.servo_j(target.tolist(), time_s=0.05, lookahead_s=0.1, gain=300)
        time.sleep(0.01)
    s = eng.snapshot()
    assert s.active_command == "servoj" and s.moving
    assert np.max(np.abs(np.array(s.q) - target)) < 0.08  # tracking the stream
    # stream stops: the watchdog brakes the arm to rest on its own
    s = _wait(eng, lambda s: not s.moving, 2.0)
    assert not s.moving and not any(s.qd)
    assert time.monotonic() - t0 < 0.6 + 1.0


def test_servo_jump_beyond_joint_speed_trips_stop(eng: MotionEngine) -> None:
    q = list(eng.snapshot().q)
    q[0] += 0.5  # 0.5 rad in 2 ms
    with pytest.raises(ProtectiveStopActiveError):
        eng.servo_j(q, time_s=CYCLE_S)
    assert eng.snapshot().safety_mode == SafetyMode.PROTECTIVE_STOP


def test_speed_j_expires_and_speed_stop(eng: MotionEngine) -> None:
    q0 = np.array(eng.snapshot().q)
    t0 = time.monotonic()
    eng.speed_j([0.4, 0, 0, 0, 0, 0], 2.0, time_s=0.4)
    s = _wait(eng, lambda s: not s.moving and time.monotonic() - t0 > 0.1, 3.0)
    elapsed = time.monotonic() - t0
    assert not s.moving
    # ramp 0.2 s up, cruise until 0.4 s, 0.2 s down: 0.4*0.1 + 0.4*0.2 + 0.4*0.1 = 0.16 rad
    assert s.q[0] - q0[0] == pytest.approx(0.16, abs=0.04)
    assert _about(elapsed, 0.6)
    # without expiry it keeps going until stopped
    eng.speed_j([0, 0, 0, 0, 0, -0.5], 5.0)
    time.sleep(0.5)
    assert eng.snapshot().moving
    eng.speed_stop(5.0)
    s = _wait(eng, lambda s: not s.moving, 2.0)
    assert not s.moving and s.q[5] < -0.15


def test_speed_l_moves_along_base_twist(eng: MotionEngine) -> None:
    p0 = np.array(eng.snapshot().tcp_pose)
    eng.speed_l([0.0, 0.0, 0.05, 0.0, 0.0, 0.0], 0.5, time_s=0.4)
    s = _wait(eng, lambda s: not s.moving and s.tcp_pose[2] > p0[2], 3.0)
    d = np.array(s.tcp_pose) - p0
    assert d[2] == pytest.approx(0.05 * 0.4, abs=0.006)
    assert np.allclose(d[:2], 0.0, atol=1e-6) and np.allclose(d[3:], 0.0, atol=1e-6)


def test_jog_in_tool_frame_follows_tool_axes(eng: MotionEngine) -> None:
    p0 = np.array(eng.snapshot().tcp_pose)
    tool_z = Rotation.from_rotvec(p0[3:]).as_matrix()[:, 2]
    assert tool_z[2] < -0.999  # about straight down at home
    eng.jog_start([0.0, 0.0, 0.05, 0.0, 0.0, 0.0], "tool", 0.5)
    time.sleep(0.3)
    eng.jog_stop()
    s = _wait(eng, lambda s: not s.moving, 2.0)
    d = np.array(s.tcp_pose) - p0
    assert np.linalg.norm(d[:3]) > 0.005
    assert np.allclose(d[:3] / np.linalg.norm(d[:3]), tool_z, atol=1e-6)
    assert np.allclose(d[3:], 0.0, atol=1e-6)
    # a jog with a client watchdog stops on its own
    eng.jog_start([0.03, 0.0, 0.0, 0.0, 0.0, 0.0], "base", 0.5, time_s=0.1)
    s = _wait(eng, lambda s: not s.moving and s.tcp_pose[0] > p0[0], 2.0)
    assert not s.moving and s.tcp_pose[0] > p0[0] + 0.001


def test_move_path_reports_progress_and_lands(eng: MotionEngine) -> None:
    q0 = np.array(eng.snapshot().q)
    q1 = _plus(q0, [0.3, 0, 0, 0, 0, 0]).tolist()
    p2 = eng.fk(q1)
    p2[2] -= 0.05
    q3 = _plus(q0, [-0.2, 0.1, 0, 0, 0, 0]).tolist()
    eng.move_path([("movej", q1, 1.5, 6.0, 0.0), ("movel", p2, 0.2, 2.0, 0.0),
                   ("movej", q3, 1.5, 6.0, 0.0)])
    progress = set()
    while (s := eng.snapshot()).moving:
        progress.add(s.async_progress)
        time.sleep(0.005)
    assert progress >= {0, 1, 2}
    assert np.allclose(eng.snapshot().q, q3, atol=1e-6)
    assert eng.snapshot().async_progress == -1


def test_speed_slider_stretches_time(eng: MotionEngine) -> None:
    q1 = _plus(np.array(HOME_Q_RAD), [0.5, 0, 0, 0, 0, 0]).tolist()
    expected = JointProfile(HOME_Q_RAD, q1, 1.0, 4.0).duration_s / 0.5
    eng.set_speed_fraction(0.5)
    t0 = time.monotonic()
    eng.move_j(q1, 1.0, 4.0)
    assert eng.wait_until_idle(10)
    assert _about(time.monotonic() - t0, expected)
    assert np.allclose(eng.snapshot().q, q1, atol=1e-6)


def test_new_move_preempts_and_stop_j(eng: MotionEngine) -> None:
    q0 = np.array(HOME_Q_RAD)
    first = eng.move_j(_plus(q0, [1.0, 0, 0, 0, 0, 0]).tolist(), 0.5, 1.0)
    time.sleep(0.4)
    q2 = _plus(q0, [0, 0.2, 0, 0, 0, 0]).tolist()
    second = eng.move_j(q2, 1.0, 2.0)
    assert eng.outcome(first) == CommandOutcome.PREEMPTED
    assert eng.wait_until_idle(10)
    assert eng.outcome(second) == CommandOutcome.SUCCEEDED
    assert np.allclose(eng.snapshot().q, q2, atol=1e-6)
    third = eng.move_j(q0.tolist(), 0.3, 1.0)
    time.sleep(0.4)
    eng.stop_j(4.0)
    assert eng.wait_until_idle(2)
    s = eng.snapshot()
    assert eng.outcome(third) == CommandOutcome.PREEMPTED
    assert not s.moving and not np.allclose(s.q, q0, atol=1e-3)
    eng.stop_l()  # always accepted, also when nothing moves


def test_joint_history_interpolates(eng: MotionEngine) -> None:
    q1 = _plus(np.array(HOME_Q_RAD), [0.4, 0, 0, 0, 0, 0]).tolist()
    eng.move_j(q1, 0.8, 2.0)
    samples = []
    while (s := eng.snapshot()).moving:
        samples.append((s.host_monotonic_s, s.q))
        time.sleep(0.02)
    for t, q in samples[::3]:
        assert np.allclose(eng.joints_at(t), q, atol=0.01)
    assert np.allclose(eng.joints_at(time.monotonic()), q1)
    with pytest.raises(LookupError):
        eng.joints_at(time.monotonic() + 1.0)
    with pytest.raises(LookupError):
        eng.joints_at(time.monotonic() - 3600.0)


def test_idle_engine_costs_little_cpu() -> None:
    with MotionEngine():
        time.sleep(0.1)
        c0 = time.process_time()
        time.sleep(1.0)
        used = time.process_time() - c0
    print(f"idle engine CPU: {used * 1000:.1f} ms per s")
    assert used < 0.05


def test_blended_linear_path_rounds_corners(eng: MotionEngine) -> None:
    p0 = list(eng.snapshot().tcp_pose)
    a = [p0[0] + 0.1, *p0[1:]]
    b = [a[0], a[1] + 0.1, *a[2:]]
    c = [b[0], b[1], b[2] - 0.1, *b[3:]]

    def run(blend: float) -> tuple[float, float, float]:
        eng.move_l(p0, 0.2, 1.0)
        assert eng.wait_until_idle(10)
        t0 = time.monotonic()
        eng.move_path([("movel", a, 0.2, 1.0, blend), ("movel", b, 0.2, 1.0, blend),
                       ("movel", c, 0.2, 1.0, 0.0)])
        closest, min_speed = 1.0, 1.0
        while (s := eng.snapshot()).moving:
            if time.monotonic() - t0 > 0.3 and s.async_progress in (0, 1):
                closest = min(closest, float(np.linalg.norm(np.subtract(s.tcp_pose[:3],
                                                                         a[:3]))))
                min_speed = min(min_speed, float(np.linalg.norm(s.tcp_speed[:3])))
            time.sleep(0.005)
        assert np.allclose(eng.snapshot().tcp_pose, c, atol=1e-6)
        return time.monotonic() - t0, closest, min_speed

    t_stop, closest_stop, _ = run(0.0)
    t_blend, closest_blend, min_speed = run(0.03)
    assert closest_stop < 0.002  # stops on the corner
    assert 0.005 < closest_blend < 0.03  # passes inside the blend radius, not through it
    assert min_speed > 0.03  # never stops at the corners
    assert t_blend < t_stop - 0.2
    with pytest.raises(CommandRejectedError):  # blend above half a segment
        eng.move_path([("movel", a, 0.2, 1.0, 0.06), ("movel", b, 0.2, 1.0, 0.0)])


# -- the controller's own clock -------------------------------------------------------------------

def test_controller_clock_catches_up_after_a_host_stall(eng: MotionEngine) -> None:
    """A host stall (here: the engine lock held for 150 ms, as a descheduled process would be)
    is caught up cycle by cycle: the pose history keeps one 2 ms step per cycle and the
    motion's speed stays what the profile says instead of jumping."""
    seen: list[tuple[float, float]] = []
    eng.set_cycle_hook(lambda: seen.append((eng.snapshot().timestamp_s, eng.snapshot().qd[0])),
                       lambda: True)
    q = _plus(eng.snapshot().q, [0.8, 0, 0, 0, 0, 0])
    cid = eng.move_j(q.tolist(), 1.0, 2.0)
    time.sleep(0.2)
    with eng._cond:  # the stall
        time.sleep(0.15)
    assert eng.wait_for(cid, 5.0) == CommandOutcome.SUCCEEDED
    eng.set_cycle_hook(None)
    stamps = np.array([t for t, _ in seen])
    steps = np.diff(stamps)
    assert np.allclose(steps[steps > 0], CYCLE_S, atol=1e-9)  # no cycle skipped
    assert max(abs(v) for _, v in seen) <= 1.0 * 1.001  # never above the profile's speed


def test_servo_burst_after_client_stall_does_not_trip(eng: MotionEngine) -> None:
    """ur_rtde's way: the program re-issues the register's latest target every cycle, the
    client writes targets at 500 Hz, stalls 60 ms, then writes its late targets back to back
    (the program sees only the last). Judged over the window, the stream has its real speed,
    so nothing trips, and the arm ends on the last target."""
    q0 = np.array(eng.snapshot().q)
    register = {"q": q0.copy(), "k": 0}

    def program_cycle() -> None:
        eng.servo_j(register["q"].tolist(), CYCLE_S, 0.1, 300)

    eng.set_cycle_hook(program_cycle, lambda: True)
    t0 = time.monotonic()
    stalled = False
    while register["k"] < 300:
        t = time.monotonic() - t0
        if t > 0.2 and not stalled:
            stalled = True
            time.sleep(0.06)
            t = time.monotonic() - t0
        k = min(int(t / CYCLE_S), 300)
        register["q"] = q0 + np.array([1.0 * CYCLE_S * k, 0, 0, 0, 0, 0])  # 1 rad/s
        register["k"] = k
        time.sleep(0.002)
    time.sleep(0.3)
    eng.set_cycle_hook(None)
    s = eng.snapshot()
    assert s.safety_mode == SafetyMode.NORMAL, s.last_stop_reason
    assert abs(s.q[0] - register["q"][0]) < 1e-3


def test_servo_tracking_lag_is_about_one_cycle(eng: MotionEngine) -> None:
    """Targets issued every controller cycle (as ur_rtde's script does): with lookahead 0.1 s
    and gain 300 the arm follows a 0.5 rad/s ramp within a few cycles of the latest target."""
    q0 = np.array(eng.snapshot().q)
    lag: list[float] = []
    count = [0]

    def cycle() -> None:
        i = count[0]
        if i >= 400:
            return
        if i > 200:
            lag.append((q0[0] + 0.5 * CYCLE_S * (i - 1) - eng.snapshot().q[0]) / (0.5 * CYCLE_S))
        eng.servo_j((q0 + np.array([0.5 * CYCLE_S * i, 0, 0, 0, 0, 0])).tolist(), CYCLE_S, 0.1,
                    300)
        count[0] += 1

    eng.set_cycle_hook(cycle, lambda: count[0] < 400)
    assert _wait(eng, lambda s: count[0] >= 400, 10.0)
    eng.set_cycle_hook(None)
    assert lag and max(abs(x) for x in lag) < 4.0
