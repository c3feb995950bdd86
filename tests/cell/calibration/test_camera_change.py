"""The camera's change from a check's views: a knock's turn counts only where the views resolve
it, so a shifted camera's figure at the tool is not thrown off by the plate's noisy tilt, and a
turned camera's turn is kept."""

from __future__ import annotations

import numpy as np
import pytest
from numpy.typing import NDArray
from scipy.spatial.transform import Rotation

from cell.calibration.camera_change import camera_change, resolved_ratio, turn_resolved
from cell.vision.frames import mean_pose
from estimator.transforms import invert_T, make_T

PLATE_CENTRE_MM = np.array([30.0, -40.0, 455.0])  # where every pivoting view sees the plate
TCP_IN_CAMERA_MM = np.array([-1.0, -59.0, 119.0])
TILT_NOISE_RAD = 0.6e-3  # a view's tilt error about the plate once its image has moved


def _views(knock: NDArray[np.float64], rng: np.random.Generator, n: int = 4
           ) -> list[NDArray[np.float64]]:
    """Each view's change of the plate in its camera frame: the knock's inverse, then the
    view's own tilt error about the plate's centre (the plate's centre stays where seen)."""
    out = []
    for _ in range(n):
        tilt = Rotation.from_rotvec([*rng.normal(0, TILT_NOISE_RAD, 2), 0.0]).as_matrix()
        about_centre = make_T(tilt, PLATE_CENTRE_MM - tilt @ PLATE_CENTRE_MM)
        out.append(about_centre @ invert_T(knock))
    return out


def _at_tool_mm(E: NDArray[np.float64]) -> NDArray[np.float64]:
    return E[:3, :3] @ TCP_IN_CAMERA_MM + E[:3, 3] - TCP_IN_CAMERA_MM


def test_the_resolved_ratio_is_the_f_distributions_upper_point() -> None:
    # F(2, 6) upper 1 %: 10.92 (tables); two views resolve only a turn far out of the noise
    assert resolved_ratio(4) == pytest.approx(10.92, abs=0.01)
    assert resolved_ratio(2) == pytest.approx(99.0)
    assert resolved_ratio(8) < resolved_ratio(4) < resolved_ratio(3)


def test_a_shifted_camera_is_a_shift_at_the_tool_whatever_the_tilt_noise() -> None:
    rng = np.random.default_rng(3)
    misses, mean_turn_misses = [], []
    for _ in range(50):
        axis = rng.normal(size=3)
        knock = make_T(np.eye(3), 0.5 * axis / np.linalg.norm(axis))
        changes = _views(knock, rng)
        truth = _at_tool_mm(invert_T(knock))
        E = camera_change(changes, [PLATE_CENTRE_MM] * len(changes))
        misses.append(float(np.linalg.norm(_at_tool_mm(E) - truth)))
        mean_turn_misses.append(float(np.linalg.norm(_at_tool_mm(mean_pose(changes)) - truth)))
    # the tilt noise carried 336 mm from the plate to the tool: ~0.1-0.3 mm with every turn kept
    assert np.median(mean_turn_misses) > 0.08
    # kept only where resolved (1 % by chance): a few hundredths of a millimetre
    assert np.median(misses) < 0.02
    assert sum(m < 0.05 for m in misses) >= 48


def test_a_turned_camera_keeps_its_turn() -> None:
    rng = np.random.default_rng(4)
    for _ in range(50):
        axis = rng.normal(size=3)
        rotvec = np.radians(0.2) * axis / np.linalg.norm(axis)
        knock = make_T(Rotation.from_rotvec(rotvec).as_matrix(), np.zeros(3))
        changes = _views(knock, rng)
        rotvecs = Rotation.from_matrix(np.stack([E[:3, :3] for E in changes])).as_rotvec()
        assert turn_resolved(rotvecs)
        E = camera_change(changes, [PLATE_CENTRE_MM] * len(changes))
        np.testing.assert_allclose(E, mean_pose(changes), atol=1e-12)


def test_views_that_agree_exactly_keep_any_turn() -> None:
    knock = make_T(Rotation.from_rotvec([1e-4, 0.0, 0.0]).as_matrix(), np.zeros(3))
    changes = [invert_T(knock)] * 3
    E = camera_change(changes, [PLATE_CENTRE_MM] * 3)
    np.testing.assert_allclose(E, invert_T(knock), atol=1e-12)
