"""Part ids across locates and the order strategies, on parts placed in the base frame."""

from __future__ import annotations

import numpy as np
import pytest

from cell.config.schema import LocateConfig
from cell.results.locate import InstanceQuality, LocatedInstance, PickOrder
from cell.results.pose import Pose
from cell.vision.instance_ids import MEMORY_LOCATES, InstanceIds
from cell.vision.pick_order import ordered
from estimator.transforms import make_T

CAMERA_DOWN = make_T(np.diag([1.0, -1.0, -1.0]), np.array([0.0, 0.0, 500.0]))


def _part(pid: int, centre: tuple[float, float, float], flags: tuple[str, ...] = ()
          ) -> LocatedInstance:
    q = InstanceQuality(rms_px=0.1, max_residual_px=0.2, ambiguous=False, converged=True,
                        identity="unique", n_points=6, n_dots=6, covariance=None)
    pose = Pose.from_T(make_T(np.eye(3), np.array(centre)))
    return LocatedInstance(id=pid, layout="target", T_base_target=pose, T_camera_target=pose,
                           centre_base_mm=centre, quality=q, flags=list(flags), reasons=[],
                           pickable=not flags)


@pytest.mark.parametrize(("order", "expected"), [
    ("nearest_to_camera_axis", [2, 3, 1]),
    ("highest", [3, 2, 1]),
    ("largest_x", [1, 3, 2]),
    ("smallest_x", [2, 3, 1]),
])
def test_each_strategy_orders_pickable_parts_first(order: PickOrder, expected: list[int]
                                                   ) -> None:
    parts = [_part(1, (200.0, 0.0, 0.0)), _part(2, (-10.0, 5.0, 10.0)),
             _part(3, (50.0, -40.0, 30.0)), _part(4, (0.0, 0.0, 90.0), ("border",))]
    assert [p.id for p in ordered(parts, order, CAMERA_DOWN)] == [*expected, 4]


def test_the_default_order_is_nearest_to_the_camera_axis() -> None:
    assert LocateConfig().order == "nearest_to_camera_axis"


def test_ids_stay_while_parts_stay_and_a_moved_part_gets_a_new_one() -> None:
    ids = InstanceIds(same_part_mm=5.0)
    a, b = np.array([0.0, 0.0, 0.0]), np.array([100.0, 0.0, 0.0])
    first = ids.assign([("target", a), ("target", b)])
    assert first == [1, 2]
    noise = np.array([1.0, -0.5, 0.3])
    assert ids.assign([("target", b + noise), ("target", a - noise)]) == [2, 1]
    assert ids.assign([("target", a), ("target", b + np.array([8.0, 0.0, 0.0]))]) == [1, 3]
    assert ids.assign([("other", a)]) == [4]  # another layout at the same place: another part


def test_a_part_hidden_for_a_few_locates_keeps_its_id_and_ids_are_never_reused() -> None:
    ids = InstanceIds(same_part_mm=5.0)
    a = np.array([0.0, 0.0, 0.0])
    assert ids.assign([("target", a)]) == [1]
    for _ in range(MEMORY_LOCATES - 1):
        ids.assign([])
    assert ids.assign([("target", a)]) == [1]
    for _ in range(MEMORY_LOCATES + 1):
        ids.assign([])
    assert ids.assign([("target", a)]) == [2]
    ids.forget()
    assert ids.assign([("target", a)]) == [3]
