"""The pick job on the simulated cell over HTTP: base-frame place poses, refusals that move
nothing, and the whole cycle against the simulator's truth."""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest
from fastapi.testclient import TestClient

from api.app import create_app
from cell.service import Cell
from estimator.transforms import T_from_pose_dict, pose_dict, pose_distance
from tests.support.cell import AUTH, running_cell, settled_tcp, sim_config, world
from tests.support.jobs import wait_job

OP, PLC = AUTH["operator"], AUTH["plc"]


def _client(tmp_path: Path, gripper: str) -> Iterator[TestClient]:
    config = sim_config(tmp_path, gripper=gripper,
                        approach={"speed_mm_s": 250.0, "accel_mm_s2": 1200.0})
    with running_cell(config) as cell, TestClient(create_app(cell)) as c:
        yield c


@pytest.fixture
def client(tmp_path: Path) -> Iterator[TestClient]:
    yield from _client(tmp_path, "sim")


def cell_of(client: TestClient) -> Cell:
    cell: Cell = client.app.state.cell  # type: ignore[attr-defined]
    return cell


def test_a_place_pose_is_taught_in_the_base_frame_without_the_camera(client: TestClient
                                                                      ) -> None:
    cell = cell_of(client)
    world(cell).set_camera_blocked(True)  # no target needed
    r = client.post("/api/v1/teach", json={"name": "tray-1", "frame": "base"}, headers=OP)
    assert r.status_code == 200, r.text
    taught = r.json()
    assert taught["frame"] == "base" and taught["T_target_tcp"] is None
    d_mm, d_deg = pose_distance(T_from_pose_dict(taught["T_base_tcp"]),
                                cell.arm_state().T_base_tcp)
    assert d_mm < 0.01 and d_deg < 0.01
    assert client.get("/api/v1/teach/tray-1", headers=OP).json()["frame"] == "base"
    # a place pose is not a tool pose relative to the target: refused, nothing moves
    r = client.post("/api/v1/approach", json={"taught": "tray-1", "wait": True}, headers=OP)
    assert r.status_code == 422 and r.json()["error"]["code"] == "taught_wrong_frame"
    assert not cell.commanded()


def test_refusals_name_the_reason_and_move_nothing(client: TestClient) -> None:
    cell = cell_of(client)
    T_before = world(cell).true_T_base_tcp()
    jobs_before = cell.jobs.count_jobs()
    # a place pose taught relative to the target is not a place pose
    r = client.post("/api/v1/teach", json={"name": "grasp-a", "samples": 2}, headers=OP)
    assert r.status_code == 200, r.text
    r = client.post("/api/v1/pick", json={"place": "grasp-a"}, headers=PLC)
    assert r.status_code == 422 and r.json()["error"]["code"] == "taught_wrong_frame"
    r = client.post("/api/v1/pick", json={"place": "nowhere"}, headers=PLC)
    assert r.status_code == 404 and r.json()["error"]["code"] == "taught_not_found"
    r = client.post("/api/v1/pick", json={"recipe": "no-such"}, headers=PLC)
    assert r.status_code == 404 and r.json()["error"]["code"] == "recipe_not_found"
    r = client.post("/api/v1/pick", json={"mode": "ibvs"}, headers=PLC)
    assert r.status_code == 422
    r = client.post("/api/v1/pick", json={"standoff_mm": "50"}, headers=PLC)
    assert r.status_code == 422
    # the part lies on the table: its grasp pose is under the workspace box's floor
    r = client.post("/api/v1/pick", json={"wait": True}, headers=PLC)
    assert r.status_code == 422, r.text
    assert "pick: grasp" in r.json()["error"]["message"]
    assert not cell.commanded() and cell.jobs.count_jobs() == jobs_before
    assert pose_distance(world(cell).true_T_base_tcp(), T_before)[0] < 1e-6
    audit = [e for e in cell.jobs.audit_log(20) if e.command == "pick"]
    assert len(audit) == 4 and all(e.outcome != "ok" for e in audit)  # refused by the cell


def test_a_cell_without_a_gripper_refuses_a_pick(tmp_path: Path) -> None:
    for c in _client(tmp_path, "none"):
        r = c.post("/api/v1/pick", json={"wait": True}, headers=PLC)
        assert r.status_code == 503 and r.json()["error"]["code"] == "gripper_unavailable"
        assert not cell_of(c).commanded()


def _raise_target(cell: Cell, dz_mm: float) -> np.ndarray:
    T = world(cell).true_T_base_target().copy()
    T[2, 3] += dz_mm
    world(cell).set_target(T)
    return T


def test_pick_and_place_on_a_raised_part(client: TestClient) -> None:
    cell = cell_of(client)
    T_part = _raise_target(cell, 60.0)
    T_place = T_part.copy()
    T_place[:3, 3] += [0.0, 150.0, 80.0]
    assert cell.sim is not None
    r = client.post("/api/v1/pick", json={"wait": True}, headers=PLC)
    job = r.json()
    assert r.status_code == 200 and job["state"] == "succeeded", job
    res = job["result"]
    assert res["grip"]["verdict"] == "held" and res["part"]["parts_seen"] == 1
    assert set(res["phases_s"]) == {"locate", "approach", "grasp", "verify", "retract"}
    assert res["cycle_s"] >= sum(v for k, v in res["phases_s"].items() if k != "locate")
    assert res["place"] is None
    grasp = T_from_pose_dict(res["grasp_T_base_tcp"])
    assert pose_distance(grasp, T_part)[0] < 0.5  # the tool pose is the part's frame
    _ = pose_dict


@pytest.mark.parametrize("phase", ["approach", "grasp", "verify", "retract", "place"])
def test_a_stop_in_each_phase_leaves_the_arm_still_and_the_job_cancelled(
        client: TestClient, phase: str) -> None:
    cell = cell_of(client)
    T_part = _raise_target(cell, 60.0)
    T_place = T_part.copy()
    T_place[:3, 3] += [0.0, 120.0, 60.0]
    r = client.post("/api/v1/teach", json={"name": "tray", "frame": "base"}, headers=OP)
    assert r.status_code == 200
    cell.taught.put(dataclasses.replace(cell.taught.get("tray"), T_base_tcp=(
        T_place @ cell.config.approach.T_target_tcp.T())))
    job = client.post("/api/v1/pick", json={"place": "tray"}, headers=PLC).json()
    deadline = time.monotonic() + 60
    # during its approach a pick's progress shows the approach's own steps
    phases = {"approach", "observe", "locate", "final"} if phase == "approach" else {phase}
    while cell.job(job["id"]).progress.get("phase") not in phases:
        assert cell.job(job["id"]).state == "running", (phase, cell.job(job["id"]).as_dict())
        assert time.monotonic() < deadline, f"the pick never reached {phase}"
        time.sleep(0.005)
    r = client.post("/api/v1/stop", json={"reason": f"stop in {phase}"}, headers=OP)
    assert r.status_code == 200 and r.json()["stopped"] is True
    still = settled_tcp(cell)
    time.sleep(0.3)
    assert pose_distance(world(cell).true_T_base_tcp(), still)[0] < 0.01
    ended = wait_job(client, job["id"], headers=OP)
    assert ended["state"] == "cancelled", ended
    assert f"pick phase {phase}" in ended["error"]["message"]
    assert "gripper left as it was" in ended["error"]["message"]
