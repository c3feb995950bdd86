"""The pick and the locate of every part through OPC UA, with asyncua as the PLC, on the
simulated cell's parts: ``Cell.LocateAll`` and its ``PartsSeen``/``PartIds`` variables against
the parts' true poses, ``Cell.Pick`` placing a part where its taught place pose says (simulator
truth), and a Machine Vision recipe whose single job is a pick (its result also as the
standard's ``ResultDataType``)."""

from __future__ import annotations

import asyncio
import json
import time
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from asyncua import ua
from fastapi.testclient import TestClient

from api.app import create_app
from api.plc.opcua import OpcUaServer
from cell.config.endpoints import opcua_cert_dir
from cell.service import Cell
from estimator.transforms import T_from_pose, T_from_pose_dict, pose_distance
from tests.api.plc.machine_vision_facts import URI as MV_URI
from tests.support.cell import AUTH, running_cell, sim_config
from tests.support.net import free_port
from tests.support.opcua import NS, Opc, opc_client
from tests.support.picking import part_at, place_parts, place_pose_for, teach_place, truth_parts

pytestmark = pytest.mark.timeout(240)


@dataclass
class Served:
    cell: Cell
    http: TestClient
    url: str


@pytest.fixture
def served(tmp_path: Path) -> Iterator[Served]:
    port = free_port()
    config = sim_config(tmp_path, gripper="sim",
                        approach={"speed_mm_s": 250.0, "accel_mm_s2": 1200.0},
                        opcua={"endpoint": f"opc.tcp://127.0.0.1:{port}"})
    with running_cell(config) as cell, TestClient(create_app(cell)) as http:
        server = OpcUaServer(cell, config.opcua, opcua_cert_dir(config))
        server.start()
        try:
            yield Served(cell, http, f"opc.tcp://127.0.0.1:{port}")
        finally:
            server.close()


def _placed_within(s: Served, goal: np.ndarray) -> dict[str, Any]:
    """The one part of the truth at ``goal``, released, within 0.3 mm / 0.1 deg of it."""
    placed = part_at(truth_parts(s.http), goal)
    assert len(placed) == 1, truth_parts(s.http)
    assert not placed[0]["held"]
    d_mm, d_deg = pose_distance(T_from_pose_dict(placed[0]["T_base_part"]), goal)
    assert d_mm <= 0.3 and d_deg <= 0.1, (d_mm, d_deg)
    return placed[0]


def test_locate_all_answers_every_part_and_the_variables_follow(served: Served) -> None:
    true_poses = place_parts(served.http, [(0.0, 0.0), (0.0, 140.0)])

    async def go() -> None:
        async with Opc(opc_client(served.url, "plc")) as opc:
            assert await opc.read("PartsSeen") == 0
            code, message, count, ids, instances = await opc.call("LocateAll", "")
            assert code == "ok", message
            assert count == 2 and len(set(ids)) == 2, (count, ids)
            parts = json.loads(instances)
            assert [p["id"] for p in parts] == ids  # the pick order
            for T_true in true_poses:
                seen = [p for p in parts if pose_distance(
                    T_from_pose_dict(p["T_base_target"]), T_true)[0] < 0.5]
                assert len(seen) == 1, (parts, T_true)
                p = seen[0]
                assert p["pickable"] is True and p["flags"] == []
                assert p["layout"] and p["quality"]["n_points"] == p["quality"]["n_dots"]
            # the variables hold the answer as it leaves
            assert await opc.read("PartsSeen") == 2
            assert list(await opc.read("PartIds")) == ids
            # the same part keeps its id in the next locate
            code, _, _, again, _ = await opc.call("LocateAll", "")
            assert code == "ok" and sorted(again) == sorted(ids)
            # a locate of every part from another door: the variables follow it
            place_parts(served.http, [(0.0, 0.0)])
            r = served.http.post("/api/v1/locate", json={"all": True}, headers=AUTH["plc"])
            assert r.status_code == 200 and len(r.json()["instances"]) == 1, r.text
            await opc.wait_for("PartsSeen", lambda v: v == 1, 10)
            assert list(await opc.read("PartIds")) == [r.json()["instances"][0]["id"]]
            # an unknown recipe is an answer, not a fault
            code, message, count, ids, instances = await opc.call("LocateAll", "no-such")
            assert code == "recipe_not_found" and count == 0 and instances == "[]", message

    asyncio.run(go())
    rows = [(e.command, e.outcome) for e in served.cell.jobs.audit_log(20)
            if e.caller == "opcua:plc(plc)"]
    assert rows.count(("locate", "ok")) == 2 and not served.cell.commanded()


def test_pick_takes_a_part_and_places_it_against_the_truth(served: Served) -> None:
    """Pick("", "", "tray"): a pick job the variables show, a JobResult with the part's id and
    the grip's verdict, and the part lying at its goal; a second Pick without a place keeps
    the next part in the gripper and leaves the other where it lies."""
    cell = served.cell
    place_parts(served.http, [(0.0, 0.0), (0.0, 140.0)])
    T_goal_part, T_place_tcp = place_pose_for(cell, -200.0, 0.0, 40.0)
    teach_place(cell, "tray", T_place_tcp)

    async def pick(opc: Opc, place: str) -> dict[str, Any]:
        code, message, job_id = await opc.call("Pick", "", "", place)
        assert code == "ok", message
        assert await opc.read("JobId") == job_id  # shown before the answer left
        assert await opc.read("JobKind") == "pick"
        assert await opc.wait_for("JobState", lambda v: v != "running", 120) == "succeeded", \
            await opc.read("JobResult")
        assert await opc.read("JobErrorCode") == ""
        ended: dict[str, Any] = json.loads(await opc.read("JobResult"))
        assert ended["job_id"] == job_id and ended["kind"] == "pick"
        return ended

    async def go(place: str) -> dict[str, Any]:
        async with Opc(opc_client(served.url, "plc")) as opc:
            return await pick(opc, place)

    placed = asyncio.run(go("tray"))
    res = placed["result"]
    assert res["grip"]["verdict"] == "held" and res["grip"]["object_detected"] is True
    assert abs(res["grip"]["width_mm"] - 40.0) < 0.5
    assert res["part"]["parts_seen"] == 2
    assert set(res["phases_s"]) == {"locate", "approach", "grasp", "verify", "retract", "place"}
    goal = T_from_pose_dict(res["place"]["T_base_part_goal"])
    assert pose_distance(goal, T_goal_part)[0] < 0.3
    _placed_within(served, goal)
    # without a place the next part stays in the gripper, the other one where it lies
    before = truth_parts(served.http)
    res = asyncio.run(go(""))["result"]
    assert res["place"] is None and res["grip"]["verdict"] == "held"
    assert "place" not in res["phases_s"]
    after = truth_parts(served.http)
    held = [p for p in after if p["held"]]
    assert len(held) == 1 and len(after) == len(before) == 2
    still = [p for p in after if not p["held"]]
    assert still[0] == next(p for p in before if p["id"] == still[0]["id"])
    rows = [(e.command, e.outcome) for e in cell.jobs.audit_log(20)
            if e.caller == "opcua:plc(plc)"]
    assert rows.count(("pick", "ok")) == 2


def test_pick_refusals_are_answers_that_move_nothing(served: Served) -> None:
    cell = served.cell
    place_parts(served.http, [(0.0, 0.0)])
    before = truth_parts(served.http)

    async def go() -> None:
        async with Opc(opc_client(served.url, "plc")) as plc, \
                Opc(opc_client(served.url, "viewer")) as viewer:
            assert (await plc.call("Pick", "", "", "nowhere"))[::2] == ["taught_not_found", ""]
            assert (await plc.call("Pick", "no-such", "", ""))[::2] == ["recipe_not_found", ""]
            assert (await viewer.call("Pick", "", "", ""))[::2] == ["forbidden", ""]
            assert (await viewer.call("LocateAll", ""))[0] == "forbidden"

    asyncio.run(go())
    assert not cell.commanded() and truth_parts(served.http) == before


PICK_RECIPE = "tray-pick"


def _recipe_content(cell: Cell, place: str) -> str:
    """The config's target as a recipe whose single job is a pick placed at ``place``."""
    t = cell.config.target
    return json.dumps({"targets": [{
        "name": "plate", "points_mm": [list(p) for p in t.points_mm],
        "dot_diameter_mm": t.dot_diameter_mm, "polarity": t.polarity,
        "standoff_mm": cell.config.approach.standoff_mm, "job": "pick", "place": place}]})


def test_machine_vision_single_job_of_a_pick_recipe_picks_and_places(served: Served) -> None:
    """A recipe whose target says ``job: "pick"``: PrepareRecipe, StartSingleJob, and the job
    is a pick; its result names the part, the grip and where the part should end, and the
    part lies there (simulator truth). A recipe that approaches still approaches."""
    cell = served.cell
    place_parts(served.http, [(0.0, 0.0), (0.0, 140.0)])
    _, T_place_tcp = place_pose_for(cell, -200.0, 0.0, 40.0)
    teach_place(cell, "tray", T_place_tcp)

    async def go() -> dict[str, Any]:
        async with Opc(opc_client(served.url, "operator")) as op, \
                Opc(opc_client(served.url, "plc")) as plc:
            ns = await plc.client.get_namespace_index(NS)
            vs = await plc.client.nodes.objects.get_child(f"{ns}:VisionSystem")
            sm = await vs.get_child(f"{ns}:VisionStateMachine")
            auto = await sm.get_child(f"{ns}:VisionAutomaticModeStateMachine")
            sub_state = await auto.get_child(f"{ns}:CurrentState")
            recipes = await vs.get_child(f"{ns}:RecipeManagement")
            results = await vs.get_child(f"{ns}:ResultManagement")
            op_recipes = op.client.get_node(recipes.nodeid)
            # a place without job "pick" is refused (invalid_recipe, 24), nothing saved
            bad = json.loads(_recipe_content(cell, "tray"))
            del bad["targets"][0]["job"]
            assert (await op_recipes.call_method(f"{ns}:AddRecipe", PICK_RECIPE, "11",
                                                 json.dumps(bad)))[1] == 24
            out = await op_recipes.call_method(f"{ns}:AddRecipe", PICK_RECIPE, "11",
                                               _recipe_content(cell, "tray"))
            assert out == [f"{PICK_RECIPE}@1", 0], out
            assert await sm.call_method(f"{ns}:SelectModeAutomatic") == 0
            assert await recipes.call_method(f"{ns}:PrepareRecipe", "11") == \
                [f"{PICK_RECIPE}@1", 0]
            job_id, error = await auto.call_method(f"{ns}:StartSingleJob", "m1", "p1", "", "")
            assert error == 0 and job_id
            assert await plc.read("JobKind") == "pick"
            assert (await sub_state.read_value()).Text == "SingleExecution"
            result_job = await results.get_child(f"{ns}:JobId")
            deadline = time.monotonic() + 120
            while await result_job.read_value() != job_id:
                assert time.monotonic() < deadline, "no result for the pick"
                await asyncio.sleep(0.05)
            assert (await sub_state.read_value()).Text == "Ready"
            body, error = await results.call_method(f"{ns}:GetResultById", f"r-{job_id}")
            assert error == 0
            last = json.loads(await (await results.get_child(f"{ns}:Result")).read_value())
            r: dict[str, Any] = json.loads(body)
            assert last == r
            # the same result through the standard's VisionSystem, as a ResultDataType
            mv = await plc.client.get_namespace_index(MV_URI)
            std = await (await plc.client.nodes.objects.get_child(f"{mv}:VisionSystem")
                         ).get_child(f"{mv}:ResultManagement")
            _, standard, error = await std.call_method(
                f"{mv}:GetResultById", ua.ResultIdDataType(Id=f"r-{job_id}"),
                ua.Variant(0, ua.VariantType.Int32))
            assert error == 0
            r["standard"] = standard
            return r

    r = asyncio.run(go())
    standard = r.pop("standard")
    assert standard.JobId.Id == r["job_id"] and standard.ResultState == 1
    assert standard.InternalRecipeId.Id == f"{PICK_RECIPE}@1"
    pose, body = [v.Value for v in standard.ResultContent]
    assert pose_distance(T_from_pose(pose.position_mm, pose.rotvec_rad),
                         T_from_pose_dict(r["pick"]["part"]["T_base_target"]))[0] < 1e-6
    assert json.loads(body)["pick"] == r["pick"]
    assert standard.ProcessingTimes.AcquisitionDuration == pytest.approx(
        1000.0 * r["pick"]["phases_s"]["locate"])
    assert r["kind"] == "pick" and r["state"] == "succeeded" and r["error_number"] == 0, r
    assert r["recipe"] == {"name": PICK_RECIPE, "number": 11, "version": 1, "target": "plate"}
    pick = r["pick"]
    assert pick["grip"]["verdict"] == "held" and pick["part"]["parts_seen"] == 2
    assert pick["place"]["taught"] == "tray"
    assert set(pick["phases_s"]) == {"locate", "approach", "grasp", "verify", "retract",
                                     "place"}
    assert pose_distance(T_from_pose_dict(r["located"]),
                         T_from_pose_dict(pick["part"]["T_base_target"]))[0] < 1e-6
    _placed_within(served, T_from_pose_dict(pick["place"]["T_base_part_goal"]))
    job = cell.job(r["job_id"])
    assert job.caller == "opcua:plc(plc)" and job.params["place"] == "tray"
