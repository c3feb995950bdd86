"""The search window policy: around the dots last seen, as wide as the arm's motion and the
target's allowed speed can have moved them; none when the sighting is too old."""

from __future__ import annotations

import numpy as np

from cell.vision.search_window import MAX_AGE_S, SearchWindows
from estimator import CameraModel, Estimator, Target
from estimator.transforms import make_T
from fakes.render import render_target

POINTS = [[0, 0, 0], [60, 0, 0], [100, 10, 0], [0, 50, 0], [40, 70, 0], [90, 60, 0]]
CAM = CameraModel(2950.0, 2950.0, 2027.5, 1519.5, (), 4056, 3040)


def test_window_holds_the_dots_and_grows_with_motion_and_age() -> None:
    target = Target(POINTS, 10.0, "dark")
    T = make_T(np.eye(3), np.array([-48.0, -32.0, 1000.0]))
    img = render_target(CAM, target, T, rng=np.random.default_rng(3))
    seen = Estimator(CAM, target).estimate(img)
    pts = np.asarray(seen.image_points_px)
    policy = SearchWindows(fixed_camera=True)
    tcp = np.eye(4)
    T_base_camera = make_T(np.eye(3), np.array([0.0, 0.0, -1000.0]))
    policy.seen(seen, target.points_mm, CAM, 10.0, tcp, T_base_camera)
    still = policy.window(10.1, tcp, CAM.width, CAM.height)
    assert still is not None
    x0, y0, x1, y1 = still
    assert (pts[:, 0] > x0).all() and (pts[:, 0] < x1).all()
    assert (pts[:, 1] > y0).all() and (pts[:, 1] < y1).all()
    assert (x1 - x0) * (y1 - y0) < 0.05 * CAM.width * CAM.height  # a small part of 12 MP
    moved = tcp.copy()
    moved[:3, 3] += [30.0, 0.0, 0.0]
    wide = policy.window(10.1, moved, CAM.width, CAM.height)
    assert wide is not None
    # 30 mm at 1 m on a 2950 px lens: ~90 px more on every side
    assert wide[0] <= x0 - 85 and wide[2] >= x1 + 85
    assert policy.window(10.0 + MAX_AGE_S + 0.1, tcp, CAM.width, CAM.height) is None
    assert policy.window(9.0, tcp, CAM.width, CAM.height) is None  # older than the sighting
    # a camera on the flange: the arm's turn sweeps the image, 2 deg is ~100 px more
    hand = SearchWindows(fixed_camera=False)
    hand.seen(seen, target.points_mm, CAM, 10.0, tcp, T_base_camera)
    turned = tcp.copy()
    c, s = np.cos(np.radians(2.0)), np.sin(np.radians(2.0))
    turned[:3, :3] = [[c, -s, 0], [s, c, 0], [0, 0, 1]]
    swept = hand.window(10.1, turned, CAM.width, CAM.height)
    assert swept is not None and swept[0] <= x0 - 100
