"""The servo's pure maths without an arm: the PBVS law and the constant-velocity filter."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from cell.motion.twist import extrapolate_tcp
from cell.servoing.servo_law import (
    LawParams,
    braking_speed,
    goal_velocity,
    integrate,
    pbvs_twist,
    pose_error,
)
from cell.servoing.target_filter import ConstantVelocityFilter
from estimator.transforms import make_T, pose_distance

P = LawParams(gain_lin_per_s=10.0, gain_rot_per_s=10.0, max_speed_mm_s=250.0,
              max_angular_speed_rad_s=np.radians(90.0), accel_mm_s2=1500.0, watchdog_s=0.08)


def _step(T: np.ndarray, twist: np.ndarray, dt: float) -> np.ndarray:
    """An ideal arm: integrates a base-frame twist (rotation about the TCP)."""
    R = Rotation.from_rotvec(twist[3:] * dt).as_matrix() @ T[:3, :3]
    return make_T(R, T[:3, 3] + twist[:3] * dt)


def _pose(rng: np.random.Generator, spread_mm: float, spread_deg: float) -> np.ndarray:
    R = Rotation.from_rotvec(np.radians(spread_deg) * rng.uniform(-1, 1, 3)).as_matrix()
    return make_T(R, rng.uniform(-spread_mm, spread_mm, 3))


def test_pose_error_is_what_takes_the_tcp_to_the_goal() -> None:
    rng = np.random.default_rng(1)
    T, G = _pose(rng, 200, 60), _pose(rng, 200, 60)
    e_p, e_r = pose_error(T, G)
    moved = make_T(Rotation.from_rotvec(e_r).as_matrix() @ T[:3, :3], T[:3, 3] + e_p)
    assert pose_distance(moved, G)[0] < 1e-9 and pose_distance(moved, G)[1] < 1e-6


@pytest.mark.parametrize("seed", range(5))
def test_law_converges_within_limits_without_overshoot(seed: int) -> None:
    rng = np.random.default_rng(seed)
    T, G = _pose(rng, 200, 60), _pose(rng, 200, 60)
    dt, prev = 0.008, np.zeros(6)
    dist = [pose_distance(T, G)[0]]
    for _ in range(int(4.0 / dt)):
        tw = pbvs_twist(T, G, np.zeros(6), prev, dt, P)
        assert np.linalg.norm(tw[:3]) <= P.max_speed_mm_s + 1e-9
        assert np.linalg.norm(tw[3:]) <= P.max_angular_speed_rad_s + 1e-9
        assert np.linalg.norm(tw[:3] - prev[:3]) <= P.accel_mm_s2 * dt + 1e-9
        assert np.linalg.norm(tw[3:] - prev[3:]) <= P.accel_mm_s2 / 1000 * dt + 1e-12
        T, prev = _step(T, tw, dt), tw
        dist.append(pose_distance(T, G)[0])
    d_mm, d_deg = pose_distance(T, G)
    assert d_mm < 1e-3 and d_deg < 1e-3
    # the translation error along the way never grows by more than numerical noise
    assert max(np.diff(dist)) < 0.05


def test_braking_speed_holds_for_the_watchdog_then_stops_at_the_goal() -> None:
    for d in (0.1, 5.0, 300.0):
        v = braking_speed(d, 1500.0, 0.08)
        assert v * 0.08 + v * v / (2 * 1500.0) == pytest.approx(d, rel=1e-9)


def test_feed_forward_follows_a_moving_goal_without_error() -> None:
    """A goal on a target moving at constant (v, w): the law with the goal's velocity as
    feed-forward keeps the TCP on it."""
    v_t, w_t = np.array([50.0, -20.0, 0.0]), np.radians([0.0, 0.0, 10.0])
    T_target = make_T(np.eye(3), np.array([-480.0, -100.0, 0.0]))
    offset = make_T(np.eye(3), np.array([30.0, 10.0, 50.0]))
    T, dt, prev = T_target @ offset, 0.004, np.zeros(6)
    prev = goal_velocity(T_target, T, v_t, w_t)
    for _ in range(500):
        G = T_target @ offset
        tw = pbvs_twist(T, G, goal_velocity(T_target, G, v_t, w_t), prev, dt, P)
        T, prev = _step(T, tw, dt), tw
        T_target = _step(T_target, np.r_[v_t, w_t], dt)
    d_mm, d_deg = pose_distance(T, T_target @ offset)
    assert d_mm < 0.05 and d_deg < 0.01


def test_extrapolate_tcp_moves_a_reading_on_by_the_twist() -> None:
    rng = np.random.default_rng(3)
    T = _pose(rng, 200, 60)
    tw = np.r_[40.0, -10.0, 5.0, np.radians([5.0, -20.0, 30.0])]
    out = extrapolate_tcp(T, tw, 0.012)
    d_mm, d_deg = pose_distance(out, _step(T, tw, 0.012))
    assert d_mm < 1e-9 and d_deg < 1e-6
    assert pose_distance(extrapolate_tcp(T, tw, -1.0), T) == (0.0, 0.0)  # never backwards


@pytest.mark.parametrize("extrapolate", [True, False])
def test_a_reading_as_old_as_a_package_costs_no_tracking_error(extrapolate: bool) -> None:
    """The law reads the TCP ``age`` late (as the arm's RTDE state is): moved on by the
    twist last sent, the TCP stays on a goal moving at 50 mm/s; read as it is, the loop
    settles with the TCP ahead of the goal by speed * age."""
    v_t, age, dt = np.array([-50.0, 0.0, 0.0]), 0.012, 0.004
    lag = round(age / dt)
    T_target = make_T(np.eye(3), np.array([-480.0, -100.0, 0.0]))
    offset = make_T(np.eye(3), np.array([0.0, 0.0, 50.0]))
    T, prev = T_target @ offset, goal_velocity(T_target, T_target @ offset, v_t, np.zeros(3))
    past = [T] * (lag + 1)
    for _ in range(750):
        G = T_target @ offset
        seen = past[-1 - lag]
        T_now = extrapolate_tcp(seen, prev, age) if extrapolate else seen
        tw = pbvs_twist(T_now, G, goal_velocity(T_target, G, v_t, np.zeros(3)), prev, dt, P)
        T, prev = _step(T, tw, dt), tw
        past.append(T)
        T_target = _step(T_target, np.r_[v_t, np.zeros(3)], dt)
    d_mm = pose_distance(T, T_target @ offset)[0]
    if extrapolate:
        assert d_mm < 0.01
    else:
        assert d_mm == pytest.approx(50.0 * age, rel=0.1)


def test_integral_is_clamped() -> None:
    i = np.zeros(3)
    for _ in range(1000):
        i = integrate(i, np.array([10.0, 0, 0]), 0.01, 20.0, 50.0)
    assert np.linalg.norm(i) * 20.0 == pytest.approx(50.0)


def _moving(t: float, v: np.ndarray, w: np.ndarray) -> np.ndarray:
    T0 = make_T(Rotation.from_rotvec([np.pi, 0, 0]).as_matrix(), np.array([-480.0, -100.0, 0.0]))
    return make_T(Rotation.from_rotvec(w * t).as_matrix() @ T0[:3, :3], T0[:3, 3] + v * t)


def test_filter_learns_a_constant_velocity_and_predicts_ahead() -> None:
    v, w = np.array([100.0, 0.0, -5.0]), np.radians([0.0, 0.0, 20.0])
    f = ConstantVelocityFilter(0.5, 0.1)
    rng = np.random.default_rng(3)
    for k in range(120):  # 4 s at 30 frames/s, jittered timing
        t = k / 30.0 + rng.uniform(0, 0.005)
        f.update(t, _moving(t, v, w))
    est = f.predict(4.1)
    assert np.allclose(est.velocity_mm_s, v, atol=0.1)
    assert np.allclose(est.angular_velocity_rad_s, w, atol=1e-3)
    d_mm, d_deg = pose_distance(est.T_base_target, _moving(4.1, v, w))
    assert d_mm < 0.05 and d_deg < 0.01


def test_filter_on_a_still_noisy_target_averages_and_keeps_velocity_small() -> None:
    f = ConstantVelocityFilter(0.5, 0.1)
    rng = np.random.default_rng(4)
    truth = _moving(0.0, np.zeros(3), np.zeros(3))
    errs = []
    for k in range(200):
        noise = make_T(Rotation.from_rotvec(rng.normal(0, 2e-4, 3)).as_matrix(),
                       rng.normal(0, 0.03, 3))
        f.update(k / 30.0, truth @ noise)
        if k > 30:
            est = f.predict(k / 30.0)
            errs.append(pose_distance(est.T_base_target, truth)[0])
            assert np.linalg.norm(est.velocity_mm_s) < 1.0
    assert float(np.sqrt(np.mean(np.square(errs)))) < 0.045  # below one frame's ~0.052 mm


def test_filter_ignores_old_measurements_and_restarts_after_a_gap() -> None:
    f = ConstantVelocityFilter(0.5, 0.1, max_dt_s=0.5)
    with pytest.raises(RuntimeError):
        f.predict(0.0)
    f.update(0.0, _moving(0.0, np.zeros(3), np.zeros(3)))
    f.update(0.1, _moving(0.1, np.array([10.0, 0, 0]), np.zeros(3)))
    n = f.updates
    f.update(0.05, _moving(5.0, np.array([10.0, 0, 0]), np.zeros(3)))  # older: ignored
    assert f.updates == n
    far = _moving(2.0, np.array([300.0, 0, 0]), np.zeros(3))
    f.update(2.0, far)  # after a long gap: taken as it is, velocity unknown (zero)
    est = f.predict(2.0)
    assert pose_distance(est.T_base_target, far)[0] < 1e-9
    assert not np.any(est.velocity_mm_s)


def test_innovation_measures_a_jump_from_the_prediction() -> None:
    f = ConstantVelocityFilter(0.5, 0.1)
    assert f.innovation(0.0, _moving(0.0, np.zeros(3), np.zeros(3))) == (0.0, 0.0)
    for k in range(10):
        f.update(k / 30.0, _moving(k / 30.0, np.array([30.0, 0, 0]), np.zeros(3)))
    ok = f.innovation(10 / 30.0, _moving(10 / 30.0, np.array([30.0, 0, 0]), np.zeros(3)))
    assert ok[0] < 0.5 and ok[1] < 0.01
    jump = _moving(10 / 30.0, np.array([30.0, 0, 0]), np.zeros(3)) @ make_T(
        Rotation.from_rotvec([0, 0, 0.1]).as_matrix(), np.array([0.0, 40.0, 0.0]))
    d_mm, d_deg = f.innovation(10 / 30.0, jump)
    assert d_mm > 35 and d_deg == pytest.approx(np.degrees(0.1), abs=0.05)


def test_filter_prediction_is_held_past_its_horizon() -> None:
    f = ConstantVelocityFilter(0.5, 0.1)
    v = np.array([100.0, 0.0, 0.0])
    for k in range(60):
        t = k / 30.0
        f.update(t, make_T(np.eye(3), v * t))
    t_last = 59 / 30.0
    near = f.predict(t_last + 0.2, max_horizon_s=0.5)
    assert np.allclose(near.velocity_mm_s, v, atol=1.0)
    far = f.predict(t_last + 3.0, max_horizon_s=0.5)
    held = f.predict(t_last + 0.5)
    assert np.allclose(far.T_base_target, held.T_base_target)  # no further than the horizon
    assert np.allclose(far.velocity_mm_s, 0.0) and np.allclose(far.angular_velocity_rad_s, 0.0)
    unbounded = f.predict(t_last + 3.0)
    assert unbounded.T_base_target[0, 3] - far.T_base_target[0, 3] == pytest.approx(250.0, abs=5)
