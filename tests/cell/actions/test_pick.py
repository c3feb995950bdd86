"""The pick job on the simulated cell over HTTP: base-frame place poses, refusals that move
nothing, and the whole cycle against the simulator's truth."""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from fastapi.testclient import TestClient

from api.app import create_app
from cell.features.teach import TaughtPose
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
    assert "pick grasp" in r.json()["error"]["message"]
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


def _place_parts(client: TestClient, offsets_mm: list[tuple[float, float]],
                 height_mm: float = 60.0) -> list[np.ndarray]:
    """Parts like the config's target, on blocks ``height_mm`` high, moved in the base
    frame from where home sees the target."""
    T0 = world(cell_of(client)).true_T_base_target()
    poses = []
    for dx, dy in offsets_mm:
        T = T0.copy()
        T[:3, 3] += [dx, dy, height_mm]
        poses.append(T)
    r = client.put("/api/v1/sim/parts", json={"parts": [pose_dict(T) for T in poses]},
                   headers=OP)
    assert r.status_code == 200, r.text
    time.sleep(0.3)  # frames exposed before the parts were placed are not of this scene
    return poses


def _teach_place(cell: Cell, name: str, T_base_tcp: np.ndarray) -> None:
    """A place pose as POST /teach {"frame": "base"} stores it, at a pose no jog reaches
    exactly."""
    cell.taught.put(TaughtPose(name, None, 1, 0.0, 0.0, None, T_base_tcp, "test", 0.0,
                               frame="base"))


def _truth(client: TestClient) -> list[dict[str, Any]]:
    parts: list[dict[str, Any]] = client.get("/api/v1/sim/truth", headers=OP).json()["parts"]
    return parts


def test_pick_and_place_two_parts_against_the_truth(client: TestClient) -> None:
    """Two parts in view: each pick takes one (a different one), holds it by the gripper's
    word and the simulator's, and puts it where the taught place pose says, within 0.3 mm
    and 0.1 deg of the part's goal (simulator truth)."""
    cell = cell_of(client)
    _place_parts(client, [(0.0, 0.0), (0.0, 140.0)])
    T_tt = cell.config.approach.T_target_tcp.T()
    picked: set[int] = set()
    T_home_part = world(cell).true_T_base_target().copy()
    for k, dy in enumerate((0.0, 130.0)):
        T_place_part = T_home_part.copy()
        T_place_part[:3, 3] += [-200.0, dy, 40.0]
        _teach_place(cell, f"tray-{k}", T_place_part @ T_tt)
        r = client.post("/api/v1/pick", json={"wait": True, "place": f"tray-{k}"}, headers=PLC)
        job = r.json()
        assert r.status_code == 200 and job["state"] == "succeeded", job
        res = job["result"]
        assert res["grip"] == {"verdict": "held", "object_detected": True, "width_mm":
                               pytest.approx(40.0, abs=0.5), "window_mm": [1.0, 84.0]}
        assert set(res["phases_s"]) == {"locate", "approach", "grasp", "verify", "retract",
                                        "place"}
        assert res["part"]["id"] not in picked
        picked.add(res["part"]["id"])
        goal = T_from_pose_dict(res["place"]["T_base_part_goal"])
        assert pose_distance(goal, T_place_part)[0] < 0.3  # the grip the cell measured
        placed = [p for p in _truth(client)
                  if pose_distance(T_from_pose_dict(p["T_base_part"]), goal)[0] < 5.0]
        assert len(placed) == 1 and not placed[0]["held"]
        d_mm, d_deg = pose_distance(T_from_pose_dict(placed[0]["T_base_part"]), goal)
        assert d_mm <= 0.3 and d_deg <= 0.1, (d_mm, d_deg)
    assert cell.gripper_ops.status()["object_detected"] is False  # opened at the place pose


def test_a_part_moved_after_the_last_look_is_a_missed_grasp(client: TestClient) -> None:
    """The part slips 8 mm once the pick has looked its last: the fingers close on nothing,
    the pick opens, retracts and fails ``grasp_missed``; the other part stays put."""
    cell = cell_of(client)
    _place_parts(client, [(0.0, 0.0), (0.0, 140.0)])
    job = client.post("/api/v1/pick", json={}, headers=PLC).json()
    deadline = time.monotonic() + 60
    while cell.job(job["id"]).progress.get("phase") != "grasp":
        assert cell.job(job["id"]).state == "running", cell.job(job["id"]).as_dict()
        assert time.monotonic() < deadline
        time.sleep(0.005)
    before = _truth(client)
    seen = T_from_pose_dict(cell.job(job["id"]).progress["part"]["T_base_target"])
    chosen = min(before, key=lambda p: pose_distance(T_from_pose_dict(p["T_base_part"]),
                                                     seen)[0])
    others = [p for p in before if p["id"] != chosen["id"]]
    T = T_from_pose_dict(chosen["T_base_part"])
    T[:3, 3] += [8.0, 0.0, 0.0]
    r = client.put("/api/v1/sim/parts", json={"parts": [
        pose_dict(T) if p["id"] == chosen["id"] else p["T_base_part"] for p in before]},
        headers=OP)
    assert r.status_code == 200
    ended = wait_job(client, job["id"], headers=OP)
    assert ended["state"] == "failed" and ended["error"]["code"] == "grasp_missed", ended
    status = cell.gripper_ops.status()
    assert status is not None and status["object_detected"] is False
    assert status["position_mm"] > 80.0  # open
    after = _truth(client)
    assert not any(p["held"] for p in after)
    for p in others:
        q = next(a for a in after if a["id"] == p["id"])
        assert pose_distance(T_from_pose_dict(q["T_base_part"]),
                             T_from_pose_dict(p["T_base_part"]))[0] < 1e-6
    # retracted: the TCP back along the tool axis from where it closed
    assert world(cell).true_T_base_tcp()[2, 3] > T[2, 3] + 50.0


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


def test_a_place_pose_out_of_the_arms_reach_is_refused_before_anything_moves(
        client: TestClient) -> None:
    """Inside the workspace box, beyond a UR5e's 850 mm: refused ``unreachable`` with the leg
    named, no job, no command, the part untouched."""
    cell = cell_of(client)
    _place_parts(client, [(0.0, 0.0)])
    T_far = world(cell).true_T_base_target() @ cell.config.approach.T_target_tcp.T()
    T_far[:3, 3] = [-820.0, 320.0, 120.0]
    _teach_place(cell, "far", T_far)
    before = _truth(client)
    jobs = cell.jobs.count_jobs()
    r = client.post("/api/v1/pick", json={"place": "far", "wait": True}, headers=PLC)
    assert r.status_code == 422, r.text
    error = r.json()["error"]
    assert error["code"] == "unreachable" and "place pose" in error["message"], error
    assert not cell.commanded() and cell.jobs.count_jobs() == jobs
    assert _truth(client) == before


def test_parts_of_a_recipes_other_target_are_not_taken_for_parts_with_dots_missing(
        client: TestClient) -> None:
    """Ten parts of a recipe's two layouts side by side in one view (the pick bench's scene):
    every choice of a pick of either target is a part of that layout, located where the
    truth has one, and the following finds it again in every frame."""
    from cell.actions.approach import JobLayout
    from cell.actions.pick import choose_part
    from cell.bench.pick import FIVE, SIX, layouts, save_recipe, scene

    cell = cell_of(client)
    save_recipe(cell)
    plates = layouts(cell)
    parts = scene(np.random.default_rng(0), 10, world(cell).true_T_base_target(), plates)
    world(cell).place_parts(parts)
    time.sleep(0.3)
    for name in (SIX, FIVE):
        lent = JobLayout(cell.core, plates[name])
        lent.apply()
        try:
            for _ in range(4):
                chosen = choose_part(cell.core, 3, plates, name)
                cell.core.locator.follow(None)
                assert chosen.layout == name and chosen.parts_seen == 10
                d_mm = min(pose_distance(chosen.located.T_base_target, p.T_base_part)[0]
                           for p in parts if p.layout_name == name)
                assert d_mm < 1.0
        finally:
            lent.ended()


def test_a_gripper_that_stops_answering_fails_the_pick_with_the_arm_still(
        client: TestClient) -> None:
    """The serial line goes quiet as the pick closes: ``gripper_fault``, the arm stopped at the
    grasp pose, nothing held; the gripper answers again and the next pick succeeds."""
    cell = cell_of(client)
    _place_parts(client, [(0.0, 0.0), (0.0, 140.0)])
    job = client.post("/api/v1/pick", json={}, headers=PLC).json()
    deadline = time.monotonic() + 60
    while cell.job(job["id"]).progress.get("phase") != "grasp":
        assert cell.job(job["id"]).state == "running", cell.job(job["id"]).as_dict()
        assert time.monotonic() < deadline
        time.sleep(0.005)
    world(cell).inject_gripper_fault("no_answer", 4)
    ended = wait_job(client, job["id"], headers=OP)
    assert ended["state"] == "failed" and ended["error"]["code"] == "gripper_fault", ended
    still = settled_tcp(cell)
    time.sleep(0.3)
    assert pose_distance(world(cell).true_T_base_tcp(), still)[0] < 0.01
    deadline = time.monotonic() + 30
    while True:  # the faults run out; the gripper answers again
        r = client.post("/api/v1/gripper", json={"action": "open"}, headers=OP)
        if r.status_code == 200:
            break
        assert time.monotonic() < deadline, r.text
        time.sleep(0.5)
    r = client.post("/api/v1/arm/home", json={"wait": True}, headers=OP)
    assert r.json()["state"] == "succeeded", r.json()
    job = client.post("/api/v1/pick", json={"wait": True}, headers=PLC).json()
    assert job["state"] == "succeeded" and job["result"]["grip"]["verdict"] == "held", job


def test_a_taught_retract_pose_ends_the_retract(client: TestClient) -> None:
    """``retract`` names a base-frame pose: the pick backs off along the tool axis, then goes
    there with the part, where the true TCP rests; the result says so."""
    cell = cell_of(client)
    _place_parts(client, [(0.0, 0.0)])
    T_retract = world(cell).true_T_base_target() @ cell.config.approach.T_target_tcp.T()
    T_retract[:3, 3] += [-120.0, 60.0, 180.0]
    _teach_place(cell, "clear", T_retract)
    job = client.post("/api/v1/pick", json={"retract": "clear", "wait": True},
                      headers=PLC).json()
    assert job["state"] == "succeeded", job
    assert job["params"]["retract"] == "clear"
    assert pose_distance(T_from_pose_dict(job["result"]["retracted_T_base_tcp"]),
                         T_retract)[0] < 1e-6
    assert pose_distance(settled_tcp(cell), T_retract)[0] < 0.5  # the arm's own accuracy
    assert [p["held"] for p in _truth(client)] == [True]
