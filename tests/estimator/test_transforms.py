"""Rotation vectors in reports: one reading per rotation, also at and near 180 degrees, while
the UR wire pose keeps SciPy's reading."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from estimator.transforms import (
    PI_BAND_RAD,
    T_from_pose,
    T_from_ur_pose,
    canonical_rotvec,
    make_T,
    pose_dict,
    ur_pose_from_T,
)

S = np.sqrt(0.5)
# axes whose rotation by pi SciPy reads with either sign, depending on the matrix's last bits
AXES = [(S, S, 0.0), (1.0, 0.0, 0.0), (0.0, 0.0, 1.0), (0.0, S, -S), (0.6, -0.8, 0.0),
        (0.0, 0.0, -1.0), (-1.0, 0.0, 0.0)]


def reading(R: Rotation) -> list[float]:
    return pose_dict(make_T(R.as_matrix(), [1.0, 2.0, 3.0]))["rotvec_rad"]


@pytest.mark.parametrize("axis", AXES)
def test_a_rotation_by_pi_reads_the_same_from_either_sign(axis: tuple[float, ...]) -> None:
    u = np.asarray(axis)
    readings = [reading(Rotation.from_rotvec(sign * np.pi * u)) for sign in (1, -1)]
    q = Rotation.from_rotvec(np.pi * u).as_quat()
    readings += [reading(Rotation.from_quat(sign * q)) for sign in (1, -1)]
    for r in readings:
        assert np.allclose(r, readings[0], atol=1e-9), readings
    lead = next(v for v in readings[0] if abs(v) > 1e-6)
    assert lead > 0 and np.isclose(np.linalg.norm(readings[0]), np.pi)


def test_the_home_pose_reads_rx_ry_plus_127_3() -> None:
    for rotvec in ([-np.pi * S, -np.pi * S, 0.0], [np.pi * S, np.pi * S, 0.0]):
        deg = np.degrees(reading(Rotation.from_rotvec(rotvec)))
        assert [f"{v:.1f}" for v in deg] == ["127.3", "127.3", "0.0"], deg


@pytest.mark.parametrize("off", [1e-7, 1e-4, 8e-4])
def test_near_pi_the_readings_of_one_reading_on_screen_agree(off: float) -> None:
    """A target at about rx 180 reads rx 180.0 on either side of pi, never -180.0."""
    for axis in AXES:
        u = np.asarray(axis)
        a = reading(Rotation.from_rotvec((np.pi - off) * u))  # just short of pi about u
        b = reading(Rotation.from_rotvec(-(np.pi - off) * u))  # just short of pi about -u
        assert np.allclose(a, b, atol=2 * off + 1e-9), (axis, a, b)
        for r, want in ((a, (np.pi - off) * u), (b, -(np.pi - off) * u)):
            assert Rotation.from_rotvec(r).approx_equal(Rotation.from_rotvec(want), atol=1e-9)
            assert np.linalg.norm(r) <= np.pi + PI_BAND_RAD


def test_the_reading_is_always_the_same_rotation() -> None:
    rng = np.random.default_rng(7)
    rots = list(Rotation.random(300, random_state=rng))
    for _ in range(300):
        u = rng.normal(size=3)
        rots.append(Rotation.from_rotvec(u / np.linalg.norm(u) * (np.pi - rng.uniform(0, 2e-3))))
    for R in rots:
        r = canonical_rotvec(R.as_matrix())
        assert Rotation.from_rotvec(r).approx_equal(R, atol=1e-9)
        angle = np.linalg.norm(r)
        assert angle <= np.pi + PI_BAND_RAD
        if np.pi - angle > PI_BAND_RAD:  # away from pi: SciPy's reading, unchanged
            assert np.allclose(r, R.as_rotvec(), atol=1e-12)
        else:
            assert next(v for v in r if abs(v) > 1e-6) > 0
        T = T_from_pose([0.0, 0.0, 0.0], r)
        assert np.allclose(T[:3, :3], R.as_matrix(), atol=1e-9)


@pytest.mark.parametrize("axis", AXES)
def test_the_ur_wire_pose_is_scipys_reading(axis: tuple[float, ...]) -> None:
    """Commands keep their meaning: the wire pose is SciPy's rotation vector as it comes."""
    for sign in (1, -1):
        R = Rotation.from_rotvec(sign * np.pi * np.asarray(axis))
        T = make_T(R.as_matrix(), [100.0, -200.0, 300.0])
        wire = ur_pose_from_T(T)
        assert wire[:3] == [0.1, -0.2, 0.3]
        assert wire[3:] == [float(v) for v in Rotation.from_matrix(T[:3, :3]).as_rotvec()]
        assert np.allclose(T_from_ur_pose(wire), T, atol=1e-9)
