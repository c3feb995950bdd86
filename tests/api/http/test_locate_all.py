"""``POST /locate {"all": true}`` on the simulated cell with several plates in one frame.

The simulated world shows one plate; here the cell's camera is given frames rendered with two
or three plates at base-frame poses the test chooses (mapped into the camera with the cell's
own mount and the arm's pose), so every answer is checked against the rendered truth."""

from __future__ import annotations

import itertools
import time
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest
from fastapi.testclient import TestClient
from scipy.spatial.transform import Rotation

from api.app import create_app
from cell.service import Cell
from drivers.camera import Frame
from estimator.transforms import T_from_pose_dict, invert_T, make_T, pose_distance
from tests.support.cell import AUTH, running_cell, sim_config
from tests.support.parts_scene import Plate, render_plates

OP = AUTH["operator"]
FLAT = np.array([[1.0, 0, 0], [0, -1, 0], [0, 0, -1]])  # plate facing up, +z into it


class _PlatesCamera:
    """The cell's camera, showing the plates it is given (each frame rendered afresh)."""

    def __init__(self, cell: Cell) -> None:
        self.model = cell.core.locator.camera_model
        self.plates: list[Plate] = []
        self.rng = np.random.default_rng(0)
        self._sequence = itertools.count(1)

    @property
    def is_connected(self) -> bool:
        return True

    def latest_frame(self, timeout_s: float = 1.0) -> Frame:
        stamp = time.monotonic() - 0.02  # inside the arm's pose history
        image = render_plates(self.model, self.plates, self.rng)
        return Frame(image, stamp, next(self._sequence), self.model)


@pytest.fixture
def cell_client(tmp_path: Path) -> Iterator[tuple[Cell, TestClient, _PlatesCamera]]:
    with running_cell(sim_config(tmp_path)) as cell, TestClient(create_app(cell)) as c:
        camera = _PlatesCamera(cell)
        cell.core.locator.camera = camera  # type: ignore[assignment]
        yield cell, c, camera


def _part_on_table(cell: Cell, u_px: float, v_px: float, spin_deg: float) -> np.ndarray:
    """T_base_part of the cell's plate lying flat on the table (base z = 0) with its dots'
    centre seen at pixel (u, v)."""
    locator = cell.core.locator
    T_base_tcp = cell.core.arm.pose_at(time.monotonic() - 0.02)
    T_base_camera = locator.frames.T_base_camera(T_base_tcp)
    m = locator.camera_model
    ray = T_base_camera[:3, :3] @ np.array([(u_px - m.cx) / m.fx, (v_px - m.cy) / m.fy, 1.0])
    origin = T_base_camera[:3, 3]
    hit = origin + ray * (-origin[2] / ray[2])
    R = Rotation.from_euler("z", spin_deg, degrees=True).as_matrix() @ FLAT
    centre = locator.target.points_mm.mean(axis=0)
    return make_T(R, hit - R @ centre)


def _show(cell: Cell, camera: _PlatesCamera, parts_T_base: list[np.ndarray]) -> None:
    """The plates at these base poses, as the camera at the arm's (still) pose sees them."""
    locator = cell.core.locator
    T_base_camera = locator.frames.T_base_camera(cell.core.arm.pose_at(time.monotonic() - 0.02))
    camera.plates = [Plate("target", locator.target, invert_T(T_base_camera) @ T)
                     for T in parts_T_base]


def _locate_all(client: TestClient) -> dict:
    r = client.post("/api/v1/locate", json={"all": True}, headers=OP)
    assert r.status_code == 200, r.text
    return r.json()


def test_every_part_with_an_id_that_stays_while_the_part_does(
        cell_client: tuple[Cell, TestClient, _PlatesCamera]) -> None:
    cell, client, camera = cell_client
    truth = [_part_on_table(cell, 330, 400, 10.0), _part_on_table(cell, 1000, 420, -35.0)]
    _show(cell, camera, truth)
    first = _locate_all(client)
    assert first["order"] == "nearest_to_camera_axis" and first["layouts"] == ["target"]
    assert len(first["instances"]) == 2 and first["unresolved"] == []
    by_truth = {}
    for inst in first["instances"]:
        dist = [pose_distance(T_from_pose_dict(inst["T_base_target"]), T) for T in truth]
        k = int(np.argmin([d[0] for d in dist]))
        assert dist[k][0] < 1.0 and dist[k][1] < 0.5, dist[k]
        assert inst["pickable"] and inst["flags"] == [] and inst["layout"] == "target"
        assert inst["quality"]["n_points"] == 6 and not inst["quality"]["ambiguous"]
        by_truth[k] = inst["id"]
    assert sorted(by_truth) == [0, 1] and by_truth[0] != by_truth[1]
    # the part at 1000 px lies further from the image centre (the camera's axis): second
    assert [i["id"] for i in first["instances"]] == [by_truth[0], by_truth[1]]

    for _ in range(3):  # new frames, new noise, the parts still: the same ids
        again = _locate_all(client)
        assert sorted(i["id"] for i in again["instances"]) == sorted(by_truth.values())

    moved = truth[1].copy()
    moved[:3, 3] += [20.0, 0.0, 0.0]  # beyond [locate] same_part_mm (5)
    _show(cell, camera, [truth[0], moved])
    after = _locate_all(client)
    ids = {i["id"] for i in after["instances"]}
    assert by_truth[0] in ids and by_truth[1] not in ids and len(ids) == 2


def test_without_all_the_answer_is_the_single_target_one(
        cell_client: tuple[Cell, TestClient, _PlatesCamera]) -> None:
    cell, client, camera = cell_client
    truth = _part_on_table(cell, 640, 400, 20.0)
    _show(cell, camera, [truth])
    r = client.post("/api/v1/locate", headers=OP)
    assert r.status_code == 200, r.text
    body = r.json()
    assert "instances" not in body and "T_base_target" in body and "consistency" in body
    assert pose_distance(T_from_pose_dict(body["T_base_target"]), truth)[0] < 1.0
    one = _locate_all(client)["instances"]
    assert len(one) == 1
    assert pose_distance(T_from_pose_dict(one[0]["T_base_target"]),
                         T_from_pose_dict(body["T_base_target"]))[0] < 0.5


def test_a_part_cut_by_the_border_is_flagged_and_an_unknown_recipe_refused(
        cell_client: tuple[Cell, TestClient, _PlatesCamera]) -> None:
    cell, client, camera = cell_client
    _show(cell, camera, [_part_on_table(cell, 500, 400, 0.0),
                         _part_on_table(cell, 1270, 400, 0.0)])
    body = _locate_all(client)
    pickable = [i for i in body["instances"] if i["pickable"]]
    flagged = [i for i in body["instances"] if not i["pickable"]] + body["unresolved"]
    assert len(pickable) == 1 and flagged
    assert all("border" in f["flags"] for f in flagged)
    assert body["instances"][0]["pickable"]  # pickable parts come first
    r = client.post("/api/v1/locate", json={"all": True, "recipe": "no-such"}, headers=OP)
    assert r.status_code == 404, r.text
