"""The simulated world's parts over HTTP: placed with PUT /sim/parts, read back from /sim/truth,
and picked for real: the gripper, driven through the cell's Modbus adapter, closes on the part
whose grasp pose is at the true TCP, which then rides with the arm until the fingers open."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from fastapi.testclient import TestClient
from numpy.typing import NDArray

from api.app import create_app
from cell.service import Cell
from estimator.transforms import T_from_pose, T_from_pose_dict, pose_distance, translation_T
from fakes.parts import GRASP_LATERAL_MM
from tests.support.cell import AUTH, running_cell, settled_tcp, sim_config

FLAT = [np.pi, 0.0, 0.0]  # dots facing up, the part's +z (into the plate) pointing down
PARTS = [{"position_mm": [-480.0, -100.0, 30.0], "rotvec_rad": FLAT},
         {"position_mm": [-380.0, -120.0, 30.0], "rotvec_rad": FLAT},
         {"position_mm": [-470.0, 20.0, 30.0], "rotvec_rad": FLAT, "width_mm": 30.0}]


@pytest.fixture
def client(tmp_path: Path) -> Iterator[TestClient]:
    with running_cell(sim_config(tmp_path, gripper="sim")) as cell, \
            TestClient(create_app(cell)) as c:
        yield c


def _cell(client: TestClient) -> Cell:
    cell: Cell = client.app.state.cell  # type: ignore[attr-defined]
    return cell


def _truth(client: TestClient) -> dict[str, Any]:
    r = client.get("/api/v1/sim/truth", headers=AUTH["viewer"])
    assert r.status_code == 200, r.text
    out: dict[str, Any] = r.json()
    return out


def _pose(d: dict[str, Any]) -> NDArray[np.float64]:
    return T_from_pose_dict(d)


def _move(cell: Cell, T_base_tcp: NDArray[np.float64]) -> None:
    with cell.core.slot.hold("test set-up"):
        cell.arm.move_linear(T_base_tcp, 200.0, 1000.0)
    settled_tcp(cell)


def _grip(client: TestClient, action: str) -> dict[str, Any]:
    r = client.post("/api/v1/gripper", json={"action": action}, headers=AUTH["operator"])
    assert r.status_code == 200, r.text
    out: dict[str, Any] = r.json()
    return out


def test_parts_are_placed_and_read_back_and_bad_input_changes_nothing(
        client: TestClient) -> None:
    r = client.put("/api/v1/sim/parts", json={"parts": PARTS}, headers=AUTH["operator"])
    assert r.status_code == 200, r.text
    placed = r.json()["parts"]
    truth = _truth(client)
    assert [p["id"] for p in truth["parts"]] == [0, 1, 2] == [p["id"] for p in placed]
    for part, asked in zip(truth["parts"], PARTS, strict=True):
        want = T_from_pose(asked["position_mm"], asked["rotvec_rad"])
        assert pose_distance(_pose(part["T_base_part"]), want) == pytest.approx((0, 0), abs=1e-6)
        assert part["held"] is False and part["layout"] is None and part["T_tcp_part"] is None
    assert [p["width_mm"] for p in truth["parts"]] == [40.0, 40.0, 30.0]
    assert pose_distance(_pose(truth["T_base_target"]),
                         _pose(truth["parts"][0]["T_base_part"]))[0] < 1e-6
    for bad, status in (({"parts": [{**PARTS[0], "layout": "no-such-recipe"}]}, 404),
                        ({"parts": [{**PARTS[0], "width_mm": 90.0}]}, 422),
                        ({"parts": []}, 422),
                        ({"parts": [{**PARTS[0], "rotvec_rad": [0, 0]}]}, 422)):
        r = client.put("/api/v1/sim/parts", json=bad, headers=AUTH["operator"])
        assert r.status_code == status, (bad, r.text)
        assert "code" in r.json()["error"], r.text
        assert _truth(client)["parts"] == truth["parts"]
    r = client.put("/api/v1/sim/parts", json={"parts": PARTS}, headers=AUTH["viewer"])
    assert r.status_code == 403
    # the single target route moves part 0 and leaves the others where they are
    r = client.put("/api/v1/sim/target", json={"position_mm": [-500.0, -90.0, 30.0],
                                               "rotvec_rad": FLAT}, headers=AUTH["operator"])
    assert r.status_code == 200, r.text
    after = _truth(client)["parts"]
    assert after[0]["T_base_part"]["position_mm"] == pytest.approx([-500.0, -90.0, 30.0])
    assert after[1:] == truth["parts"][1:]


def test_a_part_at_the_grasp_pose_is_picked_carried_and_left_where_released(
        client: TestClient) -> None:
    cell = _cell(client)
    assert client.put("/api/v1/sim/parts", json={"parts": PARTS},
                      headers=AUTH["operator"]).status_code == 200
    T_part = _pose(_truth(client)["parts"][1]["T_base_part"])
    _move(cell, T_part @ translation_T(0.0, 0.0, -60.0))  # above it, open fingers
    assert _grip(client, "open")["position_mm"] == 85.0
    _move(cell, T_part)  # the grasp pose: the part's origin, tool z along its normal
    closed = _grip(client, "close")
    assert closed["object_detected"] is True
    assert closed["position_mm"] == pytest.approx(40.0, abs=0.4)
    truth = _truth(client)
    assert [p["held"] for p in truth["parts"]] == [False, True, False]
    T_tcp_part = _pose(truth["parts"][1]["T_tcp_part"])
    assert pose_distance(T_tcp_part, np.eye(4))[0] < 0.5

    T_lifted = translation_T(20.0, 30.0, 80.0) @ T_part
    _move(cell, T_lifted)
    truth = _truth(client)
    T_tcp = _pose(truth["T_base_tcp"])
    carried = _pose(truth["parts"][1]["T_base_part"])
    d_mm, d_deg = pose_distance(carried, T_tcp @ T_tcp_part)
    assert d_mm < 1e-3 and d_deg < 1e-3
    assert pose_distance(carried, translation_T(20.0, 30.0, 80.0) @ T_part)[0] < 0.5
    assert _pose(truth["parts"][0]["T_base_part"]) == pytest.approx(
        T_from_pose(PARTS[0]["position_mm"], FLAT))  # the others stay put

    opened = _grip(client, "open")
    assert opened["object_detected"] is False and opened["position_mm"] == 85.0
    released = _truth(client)["parts"][1]
    assert released["held"] is False and released["T_tcp_part"] is None
    T_released = _pose(released["T_base_part"])
    assert pose_distance(T_released, carried)[0] < 0.5
    _move(cell, translation_T(0.0, 0.0, 60.0) @ T_lifted)
    assert pose_distance(_pose(_truth(client)["parts"][1]["T_base_part"]), T_released)[0] < 1e-6


def test_closing_away_from_every_part_finds_nothing(client: TestClient) -> None:
    cell = _cell(client)
    assert client.put("/api/v1/sim/parts", json={"parts": PARTS},
                      headers=AUTH["operator"]).status_code == 200
    T_part = _pose(_truth(client)["parts"][0]["T_base_part"])
    _grip(client, "open")
    _move(cell, T_part @ translation_T(2.0 * GRASP_LATERAL_MM, 0.0, 0.0))  # beside it
    closed = _grip(client, "close")
    assert closed["object_detected"] is False and closed["position_mm"] == 0.0
    assert not any(p["held"] for p in _truth(client)["parts"])
