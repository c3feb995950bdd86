"""The IBVS settle's carried views against known geometry: a view taken while the arm crept
near its rest pose, moved on to that pose by the arm's motion, is the view from the rest pose;
views taken farther away are left out; a hand-eye error costs microns at the TCP."""

from __future__ import annotations

import numpy as np

from cell.servoing.ibvs import Features, depths_mm, project_normalised
from cell.servoing.ibvs_mount import IbvsMount
from cell.servoing.ibvs_settle import settle_step, step_size
from cell.servoing.image import View, carried_views
from estimator.transforms import T_from_pose, invert_T

DOTS = np.array([[0, 0, 0], [60, 0, 0], [100, 10, 0], [0, 50, 0], [40, 70, 0], [90, 60, 0.0]])
T_BASE_TARGET = T_from_pose([-480.0, -130.0, 0.0], [np.pi, 0.0, 0.0])
T_TCP_CAMERA = T_from_pose([30.0, -60.0, 40.0], [0.1, -0.2, 0.05])  # the true mount
# where the arm rests: the camera 456 mm above the plate's first dot, looking at it
T_BASE_REST = T_BASE_TARGET @ invert_T(T_from_pose([-50.0, -35.0, 456.0], [0.0, 0.0, 0.0])) \
    @ invert_T(T_TCP_CAMERA)


def _view(T_base_tcp: np.ndarray, sequence: int) -> View:
    """The exact view from ``T_base_tcp`` through the true mount."""
    T_camera_target = invert_T(T_base_tcp @ T_TCP_CAMERA) @ T_BASE_TARGET
    ids = tuple(range(len(DOTS)))
    features = Features(ids, project_normalised(T_camera_target, DOTS),
                        depths_mm(T_camera_target, DOTS))
    points = DOTS @ T_camera_target[:3, :3].T + T_camera_target[:3, 3]
    return View(features, points, T_base_tcp, T_BASE_TARGET, 0.0, sequence, 100.0, ())


def _near(dp_mm: list[float], dr_rad: list[float]) -> np.ndarray:
    """The rest pose moved by ``dp_mm`` and turned by ``dr_rad`` about the TCP (base axes)."""
    T = T_BASE_REST.copy()
    T[:3, :3] = T_from_pose([0.0, 0.0, 0.0], dr_rad)[:3, :3] @ T[:3, :3]
    T[:3, 3] += dp_mm
    return T


def test_views_near_the_rest_pose_are_carried_to_it_and_far_ones_left_out() -> None:
    at_rest = _view(T_BASE_REST, 0).features
    views = [_view(_near([0.12, -0.05, 0.08], [0.0, 0.0003, -0.0002]), 1),
             _view(_near([-0.03, 0.1, 0.0], [0.0004, 0.0, 0.0]), 2),
             _view(_near([0.5, 0.0, 0.0], [0.0, 0.0, 0.0]), 3),  # 0.5 mm away
             _view(_near([0.0, 0.0, 0.0], [0.0, 0.0, 0.002]), 4)]  # 0.11 deg away
    assert np.abs(views[0].features.xy - at_rest.xy).max() * 800 > 0.1  # px: they differ
    mount = IbvsMount(False, T_TCP_CAMERA, None, None)
    carried = carried_views(views, T_BASE_REST, mount, 0.2, 0.05)
    assert len(carried) == 2
    for f in carried:
        assert np.abs(f.xy - at_rest.xy).max() * 800 < 1e-4  # px
    # switched off, not even a view taken at the rest pose itself is carried
    assert carried_views([_view(T_BASE_REST, 5)], T_BASE_REST, mount, 0.0, 0.05) == []


def test_a_hand_eye_error_costs_microns_at_the_tcp() -> None:
    """Carried through a mount 2.7 mm / 0.5 deg off the true one, views from within 0.2 mm
    ask for the same step as the rest pose's own view to a few microns at the TCP."""
    T_wrong = T_TCP_CAMERA @ T_from_pose([1.5, -1.0, 2.0],
                                         np.radians(0.5) * np.array([1.0, 1.0, 0.0]) / np.sqrt(2))
    mount = IbvsMount(False, T_wrong, None, None)
    desired = _view(_near([0.3, -0.2, 0.1], [0.0005, -0.0003, 0.0]), 0).features
    rest_step = settle_step(_view(T_BASE_REST, 0).features, desired)
    T_camera_tcp = invert_T(T_TCP_CAMERA)
    rng = np.random.default_rng(3)
    for k in range(10):
        dp = rng.normal(size=3)
        dr = rng.normal(size=3)
        v = _view(_near(list(0.15 * dp / np.linalg.norm(dp)),
                        list(np.radians(0.03) * dr / np.linalg.norm(dr))), k)
        (carried,) = carried_views([v], T_BASE_REST, mount, 0.2, 0.05)
        diff = settle_step(carried, desired) - rest_step
        assert step_size(diff, T_camera_tcp)[0] < 0.004
