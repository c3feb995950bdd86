"""The closed-form inverse of every UR model: all eight branches, the singular factors."""

from __future__ import annotations

import math

import numpy as np
import pytest

from estimator.inverse_kinematics import BRANCHES, UrInverse, branch_of, unwrap_from, wrap_near
from estimator.kinematics import UR_DH, forward


def _jacobian_det(table_name: str, q: np.ndarray) -> float:
    """det of the flange's geometric Jacobian, by finite differences of forward kinematics."""
    table = UR_DH[table_name]
    h = 1e-7
    T0 = forward(table, q)
    J = np.empty((6, 6))
    for i in range(6):
        dq = np.zeros(6)
        dq[i] = h
        T1 = forward(table, q + dq)
        J[:3, i] = (T1[:3, 3] - T0[:3, 3]) / h
        dR = T1[:3, :3] @ T0[:3, :3].T
        J[3:, i] = np.array([dR[2, 1] - dR[1, 2], dR[0, 2] - dR[2, 0], dR[1, 0] - dR[0, 1]]) / (
            2 * h)
    return float(np.linalg.det(J))


@pytest.mark.parametrize("model", sorted(UR_DH))
def test_every_branch_round_trips_random_poses(model: str) -> None:
    table = UR_DH[model]
    ik = UrInverse(table)
    rng = np.random.default_rng(7)
    seen: set[tuple[int, int, int]] = set()
    for _ in range(200):
        q = rng.uniform(-math.pi, math.pi, 6)
        T = forward(table, q)
        sols = ik.solve_all(T, float(q[5]))
        for k, branch in enumerate(BRANCHES):
            if not sols.exists[k]:
                continue
            seen.add(branch)
            assert np.allclose(forward(table, sols.q_rad[k]), T, atol=1e-7)
            factors = ik.singular_factors(sols.q_rad[k])
            assert np.allclose(factors, (sols.shoulder_mm[k], sols.sin_elbow[k],
                                         sols.sin_wrist[k]), atol=1e-6)
            assert branch_of(factors) == branch
        # the configuration the pose came from is the solution on its own branch
        own = BRANCHES.index(branch_of(ik.singular_factors(q)))
        assert np.allclose(wrap_near(sols.q_rad[own], q), q, atol=1e-7)
    assert seen == set(BRANCHES)


def test_singular_factors_are_the_jacobian_determinant() -> None:
    ik = UrInverse(UR_DH["ur5e"])
    a2, a3 = UR_DH["ur5e"].a_mm[1:3]
    rng = np.random.default_rng(2)
    for _ in range(20):
        q = rng.uniform(-math.pi, math.pi, 6)
        shoulder, s3, s5 = ik.singular_factors(q)
        assert abs(_jacobian_det("ur5e", q)) == pytest.approx(
            abs(a2 * a3 * s3 * s5 * shoulder), rel=1e-4)


def test_out_of_reach_and_inside_the_shoulder_cylinder_are_measured() -> None:
    table = UR_DH["ur5e"]
    ik = UrInverse(table)
    T = forward(table, np.array([0.0, -1.5, 1.5, -1.5, -1.5, 0.0]))
    far = T.copy()
    far[:3, 3] *= 3.0
    sols = ik.solve_all(far)
    assert not sols.exists.any()
    near_axis = T.copy()
    near_axis[:2, 3] = 0.0  # the flange over the base axis, pointing down: wrist centre too
    sols = ik.solve_all(near_axis)
    assert not sols.exists.any() and sols.inside_shoulder_mm.max() > 0


def test_wrist_aligned_keeps_the_hint() -> None:
    table = UR_DH["ur5e"]
    ik = UrInverse(table)
    q = np.array([0.3, -1.2, 1.3, -0.4, 0.0, 0.7])
    sols = ik.solve_all(forward(table, q), 0.9)
    aligned = sols.exists & (np.abs(sols.sin_wrist) < 1e-6)
    assert aligned.sum() == 4 and np.allclose(sols.q_rad[aligned][:, 5], 0.9)
    for s in sols.q_rad[sols.exists]:
        assert np.allclose(forward(table, s), forward(table, q), atol=1e-7)


def test_a_table_off_ur_structure_is_refused() -> None:
    bent = UR_DH["ur5e"].perturbed(np.zeros(6), np.zeros(6), [0.5, 0, 0, 0, 0, 0])
    with pytest.raises(ValueError, match="structure"):
        UrInverse(bent)


def test_unwrap_continues_from_the_start() -> None:
    q0 = np.array([0.0, 0.0, 0.0, 0.0, 0.0, 3.0])
    path = np.array([[0, 0, 0, 0, 0, 3.1], [0, 0, 0, 0, 0, -3.1], [0, 0, 0, 0, 0, -3.0]])
    out = unwrap_from(q0, path)
    assert np.allclose(out[:, 5], [3.1, 2 * math.pi - 3.1, 2 * math.pi - 3.0])
