"""The order parts are offered in: pickable ones first, each kind by the configured strategy.

``nearest_to_camera_axis``: the part whose dots' centre lies nearest the camera's optical
axis (at the frame's capture), the one the camera sees best and a hand camera is already
over; ``highest``: the largest base z (the top of a heap); ``largest_x`` / ``smallest_x``:
along the base x axis (a conveyor's downstream end first, or its upstream end).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence

import numpy as np

from cell.results.locate import LocatedInstance, PickOrder


def _axis_distance_mm(part: LocatedInstance, T_base_camera: np.ndarray) -> float:
    p_camera = np.linalg.solve(T_base_camera, np.append(part.centre_base_mm, 1.0))
    return float(np.hypot(p_camera[0], p_camera[1]))


def ordered(parts: Sequence[LocatedInstance], order: PickOrder,
            T_base_camera: np.ndarray) -> list[LocatedInstance]:
    """The parts in the order a pick takes them; ties (and the strategy's equals) by id."""
    keys: dict[str, Callable[[LocatedInstance], float]] = {
        "nearest_to_camera_axis": lambda p: _axis_distance_mm(p, T_base_camera),
        "highest": lambda p: -p.centre_base_mm[2],
        "largest_x": lambda p: -p.centre_base_mm[0],
        "smallest_x": lambda p: p.centre_base_mm[0],
    }
    key = keys[order]
    return sorted(parts, key=lambda p: (not p.pickable, key(p), p.id))
