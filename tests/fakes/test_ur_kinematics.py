"""UR5e kinematics and velocity profiles of the simulated controller (pure math, no threads)."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.spatial.transform import Rotation, Slerp

from estimator.transforms import T_from_pose, invert_T, pose_distance
from fakes.ur_sim.kinematics import UnreachableError, UR5eKinematics
from fakes.ur_sim.profiles import BlendedLinearPath, JointProfile, LinearProfile, Trapezoid

HOME = np.array([0.0, -1.571, 1.571, -1.571, -1.571, 0.0])


def test_fk_zero_pose_matches_published_geometry() -> None:
    # All joints at zero: the arm lies stretched along -x; flange at x = a2 + a3,
    # y = -(d4 + d6), z = d1 - d5, with the flange z axis along -y.
    T = UR5eKinematics().forward(np.zeros(6))
    assert np.allclose(T[:3, 3], [-817.2, -232.9, 62.8], atol=1e-9)
    assert np.allclose(T[:3, 2], [0.0, -1.0, 0.0], atol=1e-12)


def test_fk_home_points_the_tool_down() -> None:
    T = UR5eKinematics().forward(HOME)
    assert T[:3, 2] @ [0.0, 0.0, -1.0] > 0.9999
    # shoulder -90 deg, elbow +90 deg: upper arm vertical (d1 + |a2|), forearm horizontal,
    # wrist 1 down by d5
    assert T[2, 3] == pytest.approx(162.5 + 425.0 - 99.7, abs=0.5)
    assert T[0, 3] == pytest.approx(-392.2 - 99.6, abs=0.5)


def test_ik_round_trips_random_joints() -> None:
    kin = UR5eKinematics()
    rng = np.random.default_rng(3)
    for _ in range(300):
        q = rng.uniform(-math.pi, math.pi, 6)
        T = kin.forward(q)
        sols = kin.inverse_all(T)
        assert len(sols) in (2, 4, 6, 8)
        for s in sols:
            assert np.allclose(kin.forward(s), T, atol=1e-8)
        assert np.allclose(kin.inverse(T, q), q, atol=1e-8)
        # a seed elsewhere still gives an exact solution
        q2 = kin.inverse(T, rng.uniform(-math.pi, math.pi, 6))
        assert np.allclose(kin.forward(q2), T, atol=1e-8)


def test_ik_picks_the_2pi_equivalent_nearest_the_seed() -> None:
    kin = UR5eKinematics()
    q = HOME.copy()
    q[5] = 5.5  # beyond pi: the raw solution is 5.5 - 2 pi
    assert np.allclose(kin.inverse(kin.forward(q), q), q, atol=1e-9)


def test_ik_unreachable_raises() -> None:
    kin = UR5eKinematics()
    with pytest.raises(UnreachableError):
        kin.inverse(T_from_pose([2000.0, 0.0, 300.0], [math.pi, 0, 0]), HOME)
    # inside the reach but with the joints confined so no solution fits
    narrow = UR5eKinematics(joint_min_rad=-0.5, joint_max_rad=0.5)
    with pytest.raises(UnreachableError):
        narrow.inverse(kin.forward(HOME), np.zeros(6))


def test_ik_at_wrist_singularity_keeps_seed_joint6() -> None:
    kin = UR5eKinematics()
    q = np.array([0.3, -1.2, 1.3, -0.4, 0.0, 0.7])  # q5 = 0: axes 4 and 6 aligned
    seed = q.copy()
    seed[5] = 0.9
    sol = kin.inverse(kin.forward(q), seed)
    assert np.allclose(kin.forward(sol), kin.forward(q), atol=1e-8)
    assert sol[5] == pytest.approx(0.9)


def test_tcp_offset_applies_on_top() -> None:
    kin = UR5eKinematics()
    T_flange_tcp = T_from_pose([10.0, -5.0, 150.0], [0.0, 0.0, 0.4])
    kin.set_tcp(T_flange_tcp)
    q = np.array([0.2, -1.3, 1.5, -1.8, -1.5, 0.4])
    T_tcp = kin.forward_tcp(q)
    assert np.allclose(T_tcp, kin.forward(q) @ T_flange_tcp)
    assert np.allclose(kin.inverse_tcp(T_tcp, q), q, atol=1e-8)
    assert np.allclose(kin.forward(q), T_tcp @ invert_T(T_flange_tcp))


def test_jacobian_matches_finite_differences() -> None:
    kin = UR5eKinematics()
    kin.set_tcp(T_from_pose([0.0, 0.0, 120.0], [0.0, 0.0, 0.0]))
    q = np.array([0.2, -1.3, 1.5, -1.8, -1.5, 0.4])
    J = kin.jacobian_tcp(q)
    h = 1e-6
    T0 = kin.forward_tcp(q)
    for i in range(6):
        dq = np.zeros(6)
        dq[i] = h
        T1 = kin.forward_tcp(q + dq)
        v = (T1[:3, 3] - T0[:3, 3]) / h
        w = Rotation.from_matrix(T1[:3, :3] @ T0[:3, :3].T).as_rotvec() / h
        assert np.allclose(J[:3, i], v, atol=1e-3)
        assert np.allclose(J[3:, i], w, atol=1e-5)


# -- profiles --------------------------------------------------------------------------------


def _check_trapezoid(p: Trapezoid) -> None:
    ts = np.linspace(0.0, p.duration_s, 2001)
    s = np.array([p.at(t)[0] for t in ts])
    v = np.array([p.at(t)[1] for t in ts])
    assert np.all(np.diff(s) >= -1e-12)
    assert np.max(v) <= p.v_max + 1e-9
    acc = np.diff(v) / np.diff(ts)
    assert np.max(np.abs(acc)) <= p.a_max * (1 + 1e-6)
    assert p.at(p.duration_s) == (p.distance, 0.0, 0.0)
    # velocity is the derivative of position
    mid = len(ts) // 3
    assert (s[mid + 1] - s[mid - 1]) / (ts[mid + 1] - ts[mid - 1]) == pytest.approx(v[mid],
                                                                                    rel=1e-3)


def test_trapezoid_long_and_triangular() -> None:
    long = Trapezoid(1.0, 0.5, 2.0)
    assert long.v_peak == 0.5
    assert long.duration_s == pytest.approx(2 * 0.25 + (1.0 - 0.125) / 0.5)
    _check_trapezoid(long)
    short = Trapezoid(0.01, 0.5, 2.0)
    assert short.t_flat_s == 0.0 and short.v_peak < 0.5
    assert short.duration_s == pytest.approx(2 * math.sqrt(0.01 / 2.0))
    _check_trapezoid(short)
    assert Trapezoid(0.0, 1.0, 1.0).duration_s == 0.0
    with pytest.raises(ValueError):
        Trapezoid(1.0, 0.0, 1.0)


def test_joint_profile_synchronises_joints() -> None:
    q0 = HOME
    q1 = HOME + np.array([1.0, -0.2, 0.5, 0.0, 0.3, -0.8])
    prof = JointProfile(q0, q1, 0.8, 1.5)
    assert prof.duration_s == pytest.approx(Trapezoid(1.0, 0.8, 1.5).duration_s)
    for t in np.linspace(0.0, prof.duration_s, 50):
        q, qd, _ = prof.at(t)
        frac = (q - q0)[0] / 1.0
        assert np.allclose(q - q0, frac * (q1 - q0), atol=1e-12)  # on the joint-space line
        assert np.max(np.abs(qd)) <= 0.8 + 1e-9
    q, qd, _ = prof.at(prof.duration_s)
    assert np.array_equal(q, q1) and not np.any(qd)


def test_linear_profile_stays_on_line_and_slerps() -> None:
    T0 = T_from_pose([-400.0, -150.0, 450.0], [math.pi, 0.0, 0.0])
    T1 = T_from_pose([-300.0, 50.0, 300.0], Rotation.from_euler(
        "xyz", [180, 20, 30], degrees=True).as_rotvec())
    prof = LinearProfile(T0, T1, 250.0, 1000.0, 0.25, 1.0)
    line = T1[:3, 3] - T0[:3, 3]
    unit = line / np.linalg.norm(line)
    last_angle = 0.0
    for t in np.linspace(0.0, prof.duration_s, 60):
        T, twist = prof.at(t)
        off = T[:3, 3] - T0[:3, 3]
        assert np.linalg.norm(off - (off @ unit) * unit) < 1e-9
        assert np.linalg.norm(twist[:3]) <= 250.0 + 1e-6
        assert np.linalg.norm(twist[3:]) <= 0.25 + 1e-9
        u, _ = prof.progress(t)
        ref = Slerp([0.0, 1.0], Rotation.from_matrix(np.stack([T0[:3, :3], T1[:3, :3]])))
        assert np.allclose(T[:3, :3], ref([u]).as_matrix()[0], atol=1e-12)
        angle = pose_distance(T0, T)[1]
        assert angle >= last_angle - 1e-9
        last_angle = angle
    assert np.array_equal(prof.at(prof.duration_s)[0], T1)


def test_linear_profile_pure_rotation_takes_time() -> None:
    T0 = T_from_pose([-400.0, -150.0, 450.0], [math.pi, 0.0, 0.0])
    T1 = T0 @ T_from_pose([0.0, 0.0, 0.0], [0.0, 0.0, 0.5])
    prof = LinearProfile(T0, T1, 250.0, 1000.0, 0.25, 1.0)
    assert prof.duration_s == pytest.approx(Trapezoid(0.5, 0.25, 1.0).duration_s)
    still = LinearProfile(T0, T0, 250.0, 1000.0, 0.25, 1.0)
    assert still.duration_s == 0.0
    assert np.array_equal(still.at(0.0)[0], T0)


def test_blended_path_keeps_speed_and_ends_exactly() -> None:
    Ta = T_from_pose([-400.0, -150.0, 450.0], [math.pi, 0.0, 0.0])
    Tb = T_from_pose([-300.0, -150.0, 450.0], [math.pi, 0.0, 0.3])
    Tc = T_from_pose([-300.0, -50.0, 400.0], [math.pi, 0.0, 0.0])
    moves = [LinearProfile(Ta, Tb, 200.0, 1000.0, 0.2, 1.0),
             LinearProfile(Tb, Tc, 200.0, 1000.0, 0.2, 1.0)]
    stop = BlendedLinearPath(moves, [0.0])
    blend = BlendedLinearPath(moves, [30.0])
    assert stop.duration_s == pytest.approx(moves[0].duration_s + moves[1].duration_s)
    assert blend.duration_s < stop.duration_s - 0.1
    ts = np.linspace(0.0, blend.duration_s, 3001)
    ps = np.array([blend.pose_at(t)[:3, 3] for t in ts])
    speeds = np.linalg.norm(np.diff(ps, axis=0), axis=1) / np.diff(ts)
    assert speeds.max() <= 200.0 * 1.001
    assert np.linalg.norm(ps - Tb[:3, 3], axis=1).min() > 2.0  # the corner is cut
    assert speeds[len(speeds) // 4: 3 * len(speeds) // 4].min() > 20.0  # no stop mid-way
    assert np.array_equal(blend.pose_at(blend.duration_s), Tc)
    assert np.allclose(blend.pose_at(blend.duration_s - 1e-9), Tc, atol=1e-6)
    assert blend.index_at(0.0) == 0 and blend.index_at(blend.duration_s) == 1
