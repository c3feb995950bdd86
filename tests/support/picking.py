"""Parts and place poses for the pick tests on a simulated cell: parts like the config's target
on blocks in front of the home view (the table itself is under the workspace box's floor), base-
frame place poses, and the simulator's truth about every part."""

from __future__ import annotations

import time
from typing import Any

import numpy as np
from fastapi.testclient import TestClient
from numpy.typing import NDArray

from cell.features.teach import TaughtPose
from cell.service import Cell
from estimator.transforms import T_from_pose_dict, pose_dict, pose_distance
from tests.support.cell import AUTH, world

BLOCK_MM = 60.0  # the blocks the parts lie on


def place_parts(http: TestClient, offsets_mm: list[tuple[float, float]],
                height_mm: float = BLOCK_MM, *, T_base_origin: NDArray[np.float64] | None = None
                ) -> list[NDArray[np.float64]]:
    """Parts like the config's target on blocks ``height_mm`` high, moved in the base frame
    from where home sees the target (``PUT /sim/parts``); their true poses. Once parts lie
    in the scene the simulator's target is the first of them, so a test that places parts
    again passes the pose home saw before (``T_base_origin``)."""
    cell: Cell = http.app.state.cell  # type: ignore[attr-defined]
    T0 = world(cell).true_T_base_target() if T_base_origin is None else T_base_origin
    poses = []
    for dx, dy in offsets_mm:
        T = T0.copy()
        T[:3, 3] += [dx, dy, height_mm]
        poses.append(T)
    r = http.put("/api/v1/sim/parts", json={"parts": [pose_dict(T) for T in poses]},
                 headers=AUTH["operator"])
    assert r.status_code == 200, r.text
    time.sleep(0.3)  # frames exposed before the parts were placed are not of this scene
    return poses


def place_pose_for(cell: Cell, dx_mm: float, dy_mm: float, dz_mm: float
                   ) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """A part pose moved from where home sees the target, and the tool pose that holds a
    part there by the configured grasp (``[approach] T_target_tcp``)."""
    T_part = world(cell).true_T_base_target().copy()
    T_part[:3, 3] += [dx_mm, dy_mm, dz_mm]
    return T_part, T_part @ cell.config.approach.T_target_tcp.T()


def teach_place(cell: Cell, name: str, T_base_tcp: NDArray[np.float64]) -> None:
    """A place pose as ``POST /teach {"frame": "base"}`` stores it, at a pose no jog reaches
    exactly."""
    cell.taught.put(TaughtPose(name, None, 1, 0.0, 0.0, None, T_base_tcp, "test", 0.0,
                               frame="base"))


def truth_parts(http: TestClient) -> list[dict[str, Any]]:
    """``/sim/truth`` ``parts``: each part's id, true pose and whether the gripper holds it."""
    r = http.get("/api/v1/sim/truth", headers=AUTH["viewer"])
    assert r.status_code == 200, r.text
    parts: list[dict[str, Any]] = r.json()["parts"]
    return parts


def part_at(parts: list[dict[str, Any]], T: NDArray[np.float64], within_mm: float = 5.0
            ) -> list[dict[str, Any]]:
    """The parts of the truth within ``within_mm`` of ``T``."""
    return [p for p in parts
            if pose_distance(T_from_pose_dict(p["T_base_part"]), T)[0] < within_mm]
