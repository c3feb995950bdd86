"""Hurting the simulated cell at run time over HTTP: PUT /sim/faults knocks the camera, shifts
the lens, knocks a fixed reference plate or slips a part without the cell knowing; the cell's
locates show it against /sim/truth, and DELETE /sim/faults restores the commissioned truth."""

from __future__ import annotations

import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from fastapi.testclient import TestClient
from numpy.typing import NDArray

from api.app import create_app
from cell.service import Cell
from estimator.transforms import T_from_pose, T_from_pose_dict, invert_T, pose_distance
from tests.support.cell import AUTH, running_cell, sim_config

OP, VIEW = AUTH["operator"], AUTH["viewer"]
FLAT = [np.pi, 0.0, 0.0]


@pytest.fixture
def client(tmp_path: Path) -> Iterator[TestClient]:
    with running_cell(sim_config(tmp_path)) as cell, TestClient(create_app(cell)) as c:
        yield c


def _truth(client: TestClient) -> dict[str, Any]:
    r = client.get("/api/v1/sim/truth", headers=VIEW)
    assert r.status_code == 200, r.text
    out: dict[str, Any] = r.json()
    return out


def _faults(client: TestClient, body: dict[str, Any]) -> dict[str, Any]:
    r = client.put("/api/v1/sim/faults", json=body, headers=OP)
    assert r.status_code == 200, r.text
    out: dict[str, Any] = r.json()
    time.sleep(0.2)  # frames exposed before the fault have gone by
    return out


def _locate(client: TestClient) -> dict[str, Any]:
    r = client.post("/api/v1/locate", json={"n_frames": 3}, headers=OP)
    assert r.status_code == 200, r.text
    out: dict[str, Any] = r.json()
    return out


def _located(client: TestClient) -> NDArray[np.float64]:
    """The target's base-frame pose as the cell locates it (3 frames averaged)."""
    return T_from_pose_dict(_locate(client)["T_base_target"])


def test_a_bumped_mount_moves_the_located_target_by_the_bump_and_delete_restores_it(
        client: TestClient) -> None:
    before = _truth(client)
    T_target = T_from_pose_dict(before["T_base_target"])
    assert before["faults"] == {"camera_mount_delta": None, "lens": None,
                                "reference_delta": None, "target_slip": None}
    first = _locate(client)
    assert pose_distance(T_from_pose_dict(first["T_base_target"]), T_target)[0] < 0.3
    # where the cell believes the camera is
    T_base_camera0 = T_from_pose_dict(first["T_base_target"]) @ invert_T(
        T_from_pose_dict(first["T_camera_target"]))

    answer = _faults(client, {"camera_mount_delta": {"position_mm": [1.0, 0.0, 0.0],
                                                     "rotvec_rad": [0.0, 0.0, 0.0]}})
    truth = _truth(client)
    T_mount0 = T_from_pose_dict(before["T_flange_camera"])
    T_mount = T_from_pose_dict(truth["T_flange_camera"])
    np.testing.assert_allclose(invert_T(T_mount0) @ T_mount,
                               T_from_pose([1.0, 0.0, 0.0], [0.0, 0.0, 0.0]), atol=1e-9)
    assert answer["T_flange_camera"] == truth["T_flange_camera"]
    assert truth["faults"]["camera_mount_delta"]["position_mm"] == pytest.approx([1, 0, 0])
    assert truth["T_base_target"] == before["T_base_target"]  # the target did not move
    # the cell computes with the mount it was commissioned with: the target seems to move
    # opposite to the camera's 1 mm along its own x
    shift = _located(client)[:3, 3] - T_target[:3, 3]
    assert 0.7 < np.linalg.norm(shift) < 1.3, shift
    np.testing.assert_allclose(shift, -T_base_camera0[:3, :3] @ [1.0, 0.0, 0.0], atol=0.3)

    r = client.delete("/api/v1/sim/faults", headers=OP)
    assert r.status_code == 200, r.text
    time.sleep(0.2)
    after = _truth(client)
    assert after["T_flange_camera"] == before["T_flange_camera"]  # exactly
    assert after["camera"] == before["camera"] and after["faults"] == before["faults"]
    assert r.json()["T_flange_camera"] == before["T_flange_camera"]
    assert pose_distance(_located(client), T_target)[0] < 0.3


def test_a_shifted_lens_moves_the_located_target(client: TestClient) -> None:
    before = _truth(client)
    T_target = T_from_pose_dict(before["T_base_target"])
    z_mm = _locate(client)["T_camera_target"]["position_mm"][2]
    _faults(client, {"lens": {"principal_point_delta_px": [10.0, 0.0]}})
    truth = _truth(client)
    assert truth["camera"]["cx"] == pytest.approx(before["camera"]["cx"] + 10.0)
    assert truth["camera"]["fx"] == before["camera"]["fx"]
    assert truth["faults"]["lens"] == {"focal_scale": 1.0,
                                       "principal_point_delta_px": [10.0, 0.0]}
    # 10 px at the target's range, seen through the believed lens
    expected_mm = 10.0 / before["camera"]["fx"] * z_mm
    moved_mm = np.linalg.norm(_located(client)[:3, 3] - T_target[:3, 3])
    assert moved_mm == pytest.approx(expected_mm, rel=0.3)

    _faults(client, {"lens": {"focal_scale": 1.01}})  # replaces the shift: the focal length
    truth = _truth(client)
    assert truth["camera"]["cx"] == before["camera"]["cx"]
    assert truth["camera"]["fx"] == pytest.approx(before["camera"]["fx"] * 1.01)
    moved_mm = np.linalg.norm(_located(client)[:3, 3] - T_target[:3, 3])
    assert moved_mm == pytest.approx(0.01 * z_mm, rel=0.3)  # ~1 % of the range


def test_a_fixed_reference_is_knocked_a_part_slipped_and_both_restored(
        client: TestClient) -> None:
    parts = [{"position_mm": [-480.0, -100.0, 30.0], "rotvec_rad": FLAT},
             {"position_mm": [-300.0, -100.0, 0.0], "rotvec_rad": FLAT,
              "fixed_reference": True}]
    r = client.put("/api/v1/sim/parts", json={"parts": parts}, headers=OP)
    assert r.status_code == 200, r.text
    before = _truth(client)
    assert [p["fixed_reference"] for p in before["parts"]] == [False, True]
    knock = {"position_mm": [0.0, 0.5, 0.0], "rotvec_rad": [0.0, 0.0, 0.002]}
    slip = {"part": 0, "position_mm": [2.0, 0.0, 0.0]}
    answer = _faults(client, {"reference_delta": knock, "target_slip": slip})
    assert answer["faults"]["target_slip"]["part"] == 0
    truth = _truth(client)
    T_ref0 = T_from_pose_dict(before["parts"][1]["T_base_part"])
    np.testing.assert_allclose(T_from_pose_dict(truth["parts"][1]["T_base_part"]),
                               T_ref0 @ T_from_pose(knock["position_mm"], knock["rotvec_rad"]),
                               atol=1e-6)
    T_part0 = T_from_pose_dict(before["T_base_target"])
    np.testing.assert_allclose(T_from_pose_dict(truth["T_base_target"]),
                               T_part0 @ T_from_pose([2.0, 0.0, 0.0], [0.0, 0.0, 0.0]),
                               atol=1e-6)
    assert client.delete("/api/v1/sim/faults", headers=OP).status_code == 200
    after = _truth(client)
    assert after["parts"] == before["parts"] and after["faults"] == before["faults"]
    # a reference clamped in the cell does not drift
    r = client.put("/api/v1/sim/parts", json={"parts": [
        {**parts[1], "velocity_mm_s": [1.0, 0.0, 0.0]}]}, headers=OP)
    assert r.status_code == 422 and r.json()["error"]["code"] == "invalid_request", r.text


BAD: list[tuple[dict[str, Any], str]] = [
    ({"camera_mount_delta": {"position_mm": [1.0, 0.0]}}, "invalid_request"),
    ({"camera_mount_delta": {"position_mm": [500.0, 0.0, 0.0]}}, "invalid_request"),
    ({"camera_mount_delta": {"position_mm": [0, 0, 0], "rotvec_rad": [1.0, 0, 0]}},
     "invalid_request"),
    ({"lens": {"focal_scale": "1.01"}}, "invalid_request"),
    ({"lens": {"focal_scale": 2.0}}, "invalid_request"),
    ({"lens": {"principal_point_delta_px": [1.0, 2.0, 3.0]}}, "invalid_request"),
    ({"lens": {"fx": 1000.0}}, "invalid_request"),
    ({"camera_bump": {}}, "invalid_request"),
    ({"target_slip": {"part": 3, "position_mm": [1.0, 0.0, 0.0]}}, "invalid_sim_fault"),
    ({"reference_delta": {"position_mm": [1.0, 0.0, 0.0]}}, "invalid_sim_fault"),
]


def test_bad_bodies_are_typed_422_and_change_nothing(client: TestClient) -> None:
    _faults(client, {"camera_mount_delta": {"position_mm": [0.5, 0.0, 0.0]}})
    before = _truth(client)
    for body, code in BAD:
        r = client.put("/api/v1/sim/faults", json=body, headers=OP)
        assert r.status_code == 422, (body, r.text)
        assert r.json()["error"]["code"] == code, (body, r.text)
        after = _truth(client)
        for key in ("faults", "T_flange_camera", "camera", "parts"):
            assert after[key] == before[key], (body, key)
    assert client.put("/api/v1/sim/faults", json={}, headers=VIEW).status_code == 403
    assert client.delete("/api/v1/sim/faults", headers=VIEW).status_code == 403
    assert client.put("/api/v1/sim/faults", json={}, headers=AUTH["plc"]).status_code == 403
    assert _truth(client)["faults"] == before["faults"]


def test_off_the_simulator_there_are_no_faults_to_set(tmp_path: Path) -> None:
    with running_cell(sim_config(tmp_path)) as cell:
        _as_real_hardware(cell)
        with TestClient(create_app(cell)) as client:
            r = client.put("/api/v1/sim/faults", json={}, headers=OP)
            assert r.status_code == 404, r.text
            assert client.delete("/api/v1/sim/faults", headers=OP).status_code == 404
            assert client.get("/api/v1/sim/truth", headers=VIEW).status_code == 404


def _as_real_hardware(cell: Cell) -> None:
    """The API sees the cell as on real hardware: no simulated world to reach."""
    cell.hw.sim = None
