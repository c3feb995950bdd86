"""The OPC 40100-1 ``VisionSystem`` as a generic Machine Vision client sees it, against the facts
of the published NodeSet (:mod:`tests.api.plc.machine_vision_facts`): asyncua's client browses
every type, instance declaration, method argument and structure layout by the standard's
NodeIds, finds the instance by its type, prepares a recipe, runs a single job and reads its
result through the standard's methods and ``ResultReadyEventType``; node-opcua (another stack)
checks the same facts and runs an approach's and a pick's single job. One served cell for the
module."""

from __future__ import annotations

import asyncio
import json
import os
import subprocess
import time
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import pytest
from asyncua import Client, Node, ua
from fastapi.testclient import TestClient

from api.app import create_app
from api.plc.opcua import OpcUaServer
from cell.config.endpoints import opcua_cert_dir
from cell.features.recipes import parse_spec
from cell.results.pick import PickResult
from cell.service import Cell
from estimator.transforms import T_from_pose, T_from_pose_dict, pose_distance
from tests.api.plc.machine_vision_facts import (
    ARGUMENTS,
    DECLARATIONS,
    STATES,
    STRUCTURES,
    TYPES,
    URI,
    NodeRef,
)
from tests.api.plc.test_opcua_independent import node_opcua
from tests.support.cell import AUTH, running_cell, settled_tcp, sim_config, world
from tests.support.jobs import wait_job
from tests.support.net import free_port
from tests.support.opcua import opc_client
from tests.support.paths import REPO
from tests.support.picking import part_at, place_parts, place_pose_for, teach_place, truth_parts

SCRIPT = REPO / "tests" / "support" / "clients" / "node_opcua_machine_vision.js"
RECIPE, RECIPE_NUMBER = "plate-mv", 21
PICK_RECIPE, PICK_NUMBER = "tray-pick-mv", 22
HAND_EYE = "/api/v1/calibration/hand-eye"
RULES = {"M": ua.ObjectIds.ModellingRule_Mandatory, "O": ua.ObjectIds.ModellingRule_Optional}


@dataclass
class Served:
    cell: Cell
    http: TestClient
    url: str
    T_base_home_target: Any  # where home sees the target before any part is placed


def _save_recipe(cell: Cell, name: str, number: int, **target: Any) -> None:
    """The config's target as a recipe (set up as an operator would, over HTTP)."""
    t = cell.config.target
    cell.recipes.save(parse_spec({"name": name, "number": number, "targets": [{
        "name": "plate", "points_mm": [list(p) for p in t.points_mm],
        "dot_diameter_mm": t.dot_diameter_mm, "polarity": t.polarity, **target}]}), "test")


@pytest.fixture(scope="module")
def served(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Served]:
    tmp_path = tmp_path_factory.mktemp("mv40100")
    port = free_port()
    # brisk jobs: these tests are about what the clients read, not how the arm gets there
    config = sim_config(tmp_path, gripper="sim",
                        limits={"max_speed_mm_s": 500.0, "max_accel_mm_s2": 3000.0,
                                "max_joint_speed_deg_s": 120.0,
                                "max_joint_accel_deg_s2": 400.0},
                        approach={"speed_mm_s": 500.0, "accel_mm_s2": 3000.0,
                                  "frames_per_locate": 1, "max_cycles": 2},
                        pick={"grasp_speed_mm_s": 150.0, "place_speed_mm_s": 400.0},
                        opcua={"endpoint": f"opc.tcp://127.0.0.1:{port}"})
    with running_cell(config) as cell, TestClient(create_app(cell)) as http:
        _save_recipe(cell, RECIPE, RECIPE_NUMBER, standoff_mm=45.0)
        T_home_target = world(cell).true_T_base_target()
        _, T_place_tcp = place_pose_for(cell, -200.0, 0.0, 40.0)
        teach_place(cell, "tray", T_place_tcp)
        _save_recipe(cell, PICK_RECIPE, PICK_NUMBER,
                     standoff_mm=cell.config.approach.standoff_mm, job="pick", place="tray")
        server = OpcUaServer(cell, config.opcua, opcua_cert_dir(config))
        server.start()
        try:
            yield Served(cell, http, f"opc.tcp://127.0.0.1:{port}", T_home_target)
        finally:
            server.close()


def _node_id(ref: NodeRef | None, mv: int) -> ua.NodeId | None:
    if ref is None:
        return None
    space, number = ref
    return ua.NodeId(ua.Int32(number), ua.Int16(mv if space == "mv" else 0))


async def _references(node: Node, ref_type: int, forward: bool = True) -> list[ua.NodeId]:
    refs = await node.get_references(refs=ref_type, direction=ua.BrowseDirection.Forward
                                     if forward else ua.BrowseDirection.Inverse,
                                     includesubtypes=False)
    return [r.NodeId for r in refs]


async def _arguments(method: Node) -> tuple[list[tuple[str, ua.NodeId, int]], ...]:
    out: list[list[tuple[str, ua.NodeId, int]]] = []
    for name in ("InputArguments", "OutputArguments"):
        try:
            args = await (await method.get_child(f"0:{name}")).read_value()
        except ua.UaStatusCodeError:
            args = []
        out.append([(a.Name, a.DataType, a.ValueRank) for a in args])
    return out[0], out[1]


def _expected_args(number: int, mv: int) -> tuple[list[tuple[str, ua.NodeId, int]], ...]:
    inputs, outputs = ARGUMENTS[number]
    return ([(n, _node_id(t, mv), r) for n, t, r in inputs],  # type: ignore[misc]
            [(n, _node_id(t, mv), r) for n, t, r in outputs])


async def _check_facts(c: Client, mv: int) -> int:
    """Every fact of the table against the server's nodes; how many were checked."""
    checked = 0
    for number, name, node_class, supertype in TYPES:
        node = c.get_node(_node_id(("mv", number), mv))
        assert await node.read_browse_name() == ua.QualifiedName(name, mv), number
        assert (await node.read_node_class()).name == node_class, name
        assert await _references(node, ua.ObjectIds.HasSubtype, forward=False) == \
            [_node_id(supertype, mv)], name
        checked += 1
    for owner, number, name, node_class, type_def, data_type, rule in DECLARATIONS:
        node = c.get_node(_node_id(("mv", number), mv))
        assert await node.read_browse_name() == ua.QualifiedName(name, mv), number
        assert (await node.read_node_class()).name == node_class, name
        parents = [r.NodeId for r in await node.get_references(
            direction=ua.BrowseDirection.Inverse, refs=ua.ObjectIds.HierarchicalReferences)]
        assert _node_id(("mv", owner), mv) in parents, name
        if type_def is not None:
            assert await _references(node, ua.ObjectIds.HasTypeDefinition) == \
                [_node_id(type_def, mv)], name
        if data_type is not None:
            assert await node.read_data_type() == _node_id(data_type, mv), name
        assert await _references(node, ua.ObjectIds.HasModellingRule) == \
            ([] if rule is None else [ua.NodeId(ua.Int32(RULES[rule]))]), name
        if node_class == "Method":
            assert await _arguments(node) == _expected_args(number, mv), name
        checked += 1
    for name, (number, state_number) in STATES.items():
        state = c.get_node(_node_id(("mv", number), mv))
        assert await state.read_browse_name() == ua.QualifiedName(name, mv)
        assert await (await state.get_child("0:StateNumber")).read_value() == state_number
        checked += 1
    for number, (encoding, fields) in STRUCTURES.items():
        sdef = await c.get_node(_node_id(("mv", number), mv)).read_data_type_definition()
        assert sdef.DefaultEncodingId == _node_id(("mv", encoding), mv), number
        assert [(f.Name, f.DataType, f.ValueRank, f.IsOptional) for f in sdef.Fields] == \
            [(n, _node_id(t, mv), r, o) for n, t, r, o in fields], number
        checked += 1
    return checked


async def _instance(c: Client, mv: int) -> Node:
    """The object under Objects whose type is VisionSystemType, as a generic client finds it."""
    found = [d for d in await c.nodes.objects.get_children_descriptions()
             if d.TypeDefinition == _node_id(("mv", 1003), mv)]
    assert len(found) == 1, found
    return c.get_node(found[0].NodeId)


async def _check_instance(vs: Node, mv: int) -> dict[str, Node]:
    """Each component and method of the instance by the standard's browse names, of the
    declared type, with the type's arguments."""
    nodes: dict[str, Node] = {"VisionSystem": vs}
    path = {1003: vs}
    for owner, number, name, node_class, type_def, data_type, _ in DECLARATIONS:
        if owner not in path or name in STATES:
            continue
        child = await path[owner].get_child(f"{mv}:{name}")
        nodes[name] = child
        if node_class == "Object":
            assert type_def is not None
            assert await _references(child, ua.ObjectIds.HasTypeDefinition) == \
                [_node_id(type_def, mv)], name
            path[type_def[1]] = child
        elif node_class == "Method":
            assert await _arguments(child) == _expected_args(number, mv), name
        else:
            assert await child.read_data_type() == _node_id(data_type, mv), name
    for machine in ("VisionStateMachine", "AutomaticModeStateMachine"):
        state = await nodes[machine].get_child("0:CurrentState")
        assert await _references(state, ua.ObjectIds.HasTypeDefinition) == \
            [ua.NodeId(ua.Int32(ua.ObjectIds.FiniteStateVariableType))]
        nodes[f"{machine}.CurrentState"] = state
        nodes[f"{machine}.CurrentState.Id"] = await state.get_child("0:Id")
    return nodes


async def _state(nodes: dict[str, Node], machine: str, mv: int) -> tuple[str, ua.NodeId]:
    text = (await nodes[f"{machine}.CurrentState"].read_value()).Text
    return text, await nodes[f"{machine}.CurrentState.Id"].read_value()


class _Events:
    def __init__(self) -> None:
        self.events: list[Any] = []

    def event_notification(self, event: Any) -> None:
        self.events.append(event)


def test_asyncua_client_finds_the_facet_by_the_standards_facts(served: Served) -> None:
    """Every type, declaration, argument list, state and structure layout of the facts table,
    the instance found by its type with the standard's components, and the state machines'
    states with their Ids."""

    async def go() -> None:
        async with opc_client(served.url, "plc") as c:
            await c.load_data_type_definitions()
            mv = await c.get_namespace_index(URI)
            assert await _check_facts(c, mv) == \
                len(TYPES) + len(DECLARATIONS) + len(STATES) + len(STRUCTURES)
            nodes = await _check_instance(await _instance(c, mv), mv)
            text, state_id = await _state(nodes, "VisionStateMachine", mv)
            assert (text, state_id) == ("Preoperational", _node_id(("mv", 5028), mv))
            configs = nodes["ConfigurationManagement"]
            config = await (await configs.get_child(f"{mv}:ActiveConfiguration")).read_value()
            assert config.InternalId.Id == "config"  # no calibration applied: the file's
            listed = await configs.call_method(
                f"{mv}:GetConfigurationList", ua.Variant(0, ua.VariantType.UInt32),
                ua.Variant(0, ua.VariantType.UInt32), ua.Variant(0, ua.VariantType.Int32))
            assert listed[0] is True and listed[1] == 1 and listed[3] == [config] \
                and listed[-1] == 0
            _, by_id, error = await configs.call_method(
                f"{mv}:GetConfigurationById", ua.ConfigurationIdDataType(Id="config"),
                ua.Variant(0, ua.VariantType.Int32))
            assert (by_id, error) == (config, 0)
            assert await configs.call_method(f"{mv}:ActivateConfiguration",
                                             ua.ConfigurationIdDataType(Id="config")) == 0
            assert await configs.call_method(f"{mv}:ActivateConfiguration",
                                             ua.ConfigurationIdDataType(Id="other")) != 0

    asyncio.run(go())


def test_asyncua_client_runs_a_single_job_and_reads_its_result(served: Served) -> None:
    """SelectModeAutomatic, PrepareRecipe by the recipe's number, StartSingleJob with the
    standard's id structures; the job is the recipe's approach, and its end raises
    ResultReadyEvent with the mandatory fields; GetResultById, GetResultComponentsById and
    GetResultListFiltered answer the same ResultDataType: the located pose (against the
    simulator's truth) and the job's processing times."""
    cell = served.cell

    async def go() -> None:
        async with opc_client(served.url, "plc") as c:
            await c.load_data_type_definitions()
            mv = await c.get_namespace_index(URI)
            nodes = await _check_instance(await _instance(c, mv), mv)
            sm, auto = nodes["VisionStateMachine"], nodes["AutomaticModeStateMachine"]
            recipes, results = nodes["RecipeManagement"], nodes["ResultManagement"]
            events = _Events()
            sub = await c.create_subscription(20, events)
            await sub.subscribe_events(nodes["VisionSystem"], c.get_node(
                _node_id(("mv", 1024), mv)))

            assert await sm.call_method(f"{mv}:SelectModeAutomatic") == 0
            assert await _state(nodes, "AutomaticModeStateMachine", mv) == \
                ("Initialized", _node_id(("mv", 5056), mv))
            out = await recipes.call_method(
                f"{mv}:AddRecipe", ua.RecipeIdExternalDataType(Id=RECIPE),
                ua.ProductIdDataType(Id=""))
            assert out[0].Id == f"{RECIPE}@1" and out[3] is False and out[-1] == 0, out
            internal, completed, error = await recipes.call_method(
                f"{mv}:PrepareRecipe", ua.RecipeIdExternalDataType(Id=str(RECIPE_NUMBER)),
                ua.RecipeIdInternalDataType(Id=""))
            assert (internal.Id, completed, error) == (f"{RECIPE}@1", True, 0)
            assert (await _state(nodes, "AutomaticModeStateMachine", mv))[0] == "Ready"
            listed = await recipes.call_method(
                f"{mv}:GetRecipeListFiltered", ua.RecipeIdExternalDataType(Id=""),
                ua.ProductIdDataType(Id=""), ua.Variant(1, ua.VariantType.Int32),
                ua.Variant(0, ua.VariantType.UInt32), ua.Variant(0, ua.VariantType.UInt32),
                ua.Variant(0, ua.VariantType.Int32))
            assert [r.Id for r in listed[3]] == [f"{RECIPE}@1"] and listed[-1] == 0

            job, error = await auto.call_method(
                f"{mv}:StartSingleJob", ua.MeasIdDataType(Id="meas-1"),
                ua.PartIdDataType(Id="part-1"), ua.RecipeIdExternalDataType(Id=""),
                ua.ProductIdDataType(Id="product-1"), ua.Variant([], ua.VariantType.Variant))
            assert error == 0 and job.Id
            assert cell.job(job.Id).kind == "approach"
            deadline = time.monotonic() + 60
            while not events.events:
                assert time.monotonic() < deadline, "no ResultReadyEvent"
                await asyncio.sleep(0.05)
            event = events.events[0]
            assert event.JobId.Id == job.Id and event.ResultId.Id == f"r-{job.Id}"
            assert event.IsPartial is False and event.ResultState == 1
            assert event.InternalRecipeId.Id == f"{RECIPE}@1"
            assert event.InternalConfigurationId.Id == "config"
            assert event.CreationTime > ua.get_win_epoch()
            assert event.MeasId.Id == "meas-1" and event.PartId.Id == "part-1"
            assert (await _state(nodes, "AutomaticModeStateMachine", mv))[0] == "Ready"

            _, result, error = await results.call_method(
                f"{mv}:GetResultById", ua.ResultIdDataType(Id=f"r-{job.Id}"),
                ua.Variant(0, ua.VariantType.Int32))
            assert error == 0 and result.JobId.Id == job.Id and result.ResultState == 1
            assert result.ProductId.Id == "product-1" and result.IsSimulated is True
            pose, body = [v.Value for v in result.ResultContent]
            assert cell.sim is not None
            d_mm, _ = pose_distance(T_from_pose(pose.position_mm, pose.rotvec_rad),
                                    cell.sim.true_T_base_target())
            assert d_mm < 1.0
            assert json.loads(body)["kind"] == "approach"
            times = result.ProcessingTimes
            record = cell.job(job.Id)
            assert record.ended_at is not None
            assert times.EndTime.timestamp() == pytest.approx(record.ended_at, abs=1e-3)
            assert times.ProcessingDuration == pytest.approx(
                1000.0 * (record.ended_at - record.created_at), abs=1.0)
            assert 0.0 < times.AcquisitionDuration <= times.ProcessingDuration

            components = await results.call_method(
                f"{mv}:GetResultComponentsById", ua.ResultIdDataType(Id=f"r-{job.Id}"),
                ua.Variant(0, ua.VariantType.Int32))
            assert components[-1] == 0 and components[12].Id == job.Id  # JobId
            assert components[4] == 1 and components[5].Id == "meas-1"
            found = await results.call_method(
                f"{mv}:GetResultListFiltered", ua.Variant(0, ua.VariantType.Int32),
                ua.MeasIdDataType(Id="meas-1"), ua.PartIdDataType(Id=""),
                ua.RecipeIdExternalDataType(Id=""), ua.RecipeIdInternalDataType(Id=""),
                ua.ConfigurationIdDataType(Id=""), ua.ConfigurationIdDataType(Id=""),
                ua.ProductIdDataType(Id=""), ua.JobIdDataType(Id=""),
                ua.Variant(0, ua.VariantType.UInt32), ua.Variant(0, ua.VariantType.UInt32),
                ua.Variant(0, ua.VariantType.Int32))
            assert [r.ResultId.Id for r in found[3]] == [f"r-{job.Id}"] and found[-1] == 0
            for method, n_out in (("GetResultById", 3), ("GetResultComponentsById", 17)):
                refused = await results.call_method(
                    f"{mv}:{method}", ua.ResultIdDataType(Id="r-nothing"),
                    ua.Variant(0, ua.VariantType.Int32))
                assert len(refused) == n_out and refused[-1] == 25  # result_not_found
            await sub.delete()

    asyncio.run(go())
    settled_tcp(cell)


def test_node_opcua_checks_the_facts_and_runs_an_approach_then_a_pick(served: Served,
                                                                     tmp_path: Path) -> None:
    """node-opcua reads every fact of the table by the standard's NodeIds (browse names, node
    classes, method arguments, state numbers, structure layouts), finds VisionSystem by its
    type, and runs two single jobs through the standard's methods: a recipe whose job is an
    approach, then one whose job is a pick. It takes each ResultReadyEvent and decodes the
    ResultDataType GetResultById answers: the located pose (simulator truth), then the picked
    part's pose; the part lies at its place (simulator truth)."""
    facts = {
        "nodes": [["mv", i, name, node_class] for i, name, node_class, _ in TYPES]
        + [["mv", i, name, node_class] for _, i, name, node_class, *_ in DECLARATIONS],
        "arguments": [[i, [[[n, list(t), r] for n, t, r in args] for args in lists]]
                      for i, lists in ARGUMENTS.items()],
        "states": [[name, i, number] for name, (i, number) in STATES.items()],
        "structures": [[i, ["mv", encoding], [[n, list(t), r, o] for n, t, r, o in fields]]
                       for i, (encoding, fields) in STRUCTURES.items()]}
    n_facts = sum(len(rows) for rows in facts.values())
    facts_file = tmp_path / "facts.json"
    facts_file.write_text(json.dumps(facts))
    folder = node_opcua()
    cell = served.cell
    assert cell.home("test", speed_deg_s=120.0, wait=True).state == "succeeded"  # home sees parts
    (T_base_part,) = place_parts(served.http, [(0.0, 0.0)],
                                 T_base_origin=served.T_base_home_target)
    env = {**os.environ, "NODE_PATH": str(folder / "node_modules")}
    done = subprocess.run(["node", str(SCRIPT), served.url, "plc", "sim-plc",
                           f"{RECIPE_NUMBER},{PICK_NUMBER}", str(facts_file)],
                          capture_output=True, text=True, timeout=300, env=env, check=False)
    assert done.returncode == 0, done.stderr[-2000:]
    out = json.loads(done.stdout.strip().splitlines()[-1])
    assert out["facts"] == {"checked": n_facts, "mismatches": []}, out["facts"]
    approached, picked = out["jobs"]

    job = cell.job(approached["jobId"])
    assert job.kind == "approach" and job.state == "succeeded", job.error_message
    assert approached["prepared"] == f"{RECIPE}@1"
    assert approached["event"] == {"jobId": job.id, "resultId": f"r-{job.id}",
                                   "resultState": 1}
    assert approached["result"]["measId"] == "node-meas-0"
    d_mm, _ = pose_distance(T_from_pose(approached["result"]["position_mm"],
                                        approached["result"]["rotvec_rad"]), T_base_part)
    assert d_mm < 1.0

    out = picked
    job = cell.job(out["jobId"])
    assert job.kind == "pick" and job.state == "succeeded", job.error_message
    assert out["prepared"] == f"{PICK_RECIPE}@1"
    assert out["event"] == {"jobId": job.id, "resultId": f"r-{job.id}", "resultState": 1}
    assert out["result"]["jobId"] == job.id and out["result"]["resultState"] == 1
    assert out["result"]["measId"] == "node-meas-1"
    pick = job.result
    assert isinstance(pick, PickResult)
    d_mm, _ = pose_distance(T_from_pose(out["result"]["position_mm"],
                                        out["result"]["rotvec_rad"]),
                            pick.part.T_base_target.T())
    assert d_mm < 1e-6
    assert pick.place is not None
    placed = part_at(truth_parts(served.http), pick.place.T_base_part_goal.T())
    assert len(placed) == 1 and not placed[0]["held"]
    assert pose_distance(T_from_pose_dict(placed[0]["T_base_part"]),
                         pick.place.T_base_part_goal.T())[0] <= 0.3
    settled_tcp(cell)


def test_asyncua_client_runs_a_pick_recipes_single_job(served: Served) -> None:
    """A recipe whose single job is a pick, through the standard's methods: the job is a pick,
    its ResultDataType carries the picked part's pose and the job's processing times, and the
    part lies at its place (simulator truth)."""
    cell = served.cell
    assert cell.home("test", speed_deg_s=120.0, wait=True).state == "succeeded"  # home sees parts
    (T_base_part,) = place_parts(served.http, [(0.0, 0.0)],
                                 T_base_origin=served.T_base_home_target)

    async def go() -> str:
        async with opc_client(served.url, "plc") as c:
            await c.load_data_type_definitions()
            mv = await c.get_namespace_index(URI)
            nodes = await _check_instance(await _instance(c, mv), mv)
            events = _Events()
            sub = await c.create_subscription(20, events)
            await sub.subscribe_events(nodes["VisionSystem"], c.get_node(
                _node_id(("mv", 1024), mv)))
            assert await nodes["VisionStateMachine"].call_method(
                f"{mv}:SelectModeAutomatic") == 0
            internal, completed, error = await nodes["RecipeManagement"].call_method(
                f"{mv}:PrepareRecipe", ua.RecipeIdExternalDataType(Id=PICK_RECIPE),
                ua.RecipeIdInternalDataType(Id=""))
            assert (internal.Id, completed, error) == (f"{PICK_RECIPE}@1", True, 0)
            job, error = await nodes["AutomaticModeStateMachine"].call_method(
                f"{mv}:StartSingleJob", ua.MeasIdDataType(Id="meas-pick"),
                ua.PartIdDataType(Id="part-7"), ua.RecipeIdExternalDataType(Id=""),
                ua.ProductIdDataType(Id=""), ua.Variant([], ua.VariantType.Variant))
            assert error == 0 and cell.job(job.Id).kind == "pick"
            deadline = time.monotonic() + 120
            while not any(e.JobId.Id == job.Id for e in events.events):
                assert time.monotonic() < deadline, "no ResultReadyEvent"
                await asyncio.sleep(0.05)
            event = next(e for e in events.events if e.JobId.Id == job.Id)
            assert event.ResultState == 1 and event.InternalRecipeId.Id == f"{PICK_RECIPE}@1"
            _, result, error = await nodes["ResultManagement"].call_method(
                f"{mv}:GetResultById", ua.ResultIdDataType(Id=f"r-{job.Id}"),
                ua.Variant(0, ua.VariantType.Int32))
            assert error == 0 and result.ResultState == 1 and result.PartId.Id == "part-7"
            pose, body = [v.Value for v in result.ResultContent]
            d_mm, _ = pose_distance(T_from_pose(pose.position_mm, pose.rotvec_rad), T_base_part)
            assert d_mm < 1.0
            assert json.loads(body)["kind"] == "pick"
            record = cell.job(job.Id)
            assert record.ended_at is not None
            assert result.ProcessingTimes.ProcessingDuration == pytest.approx(
                1000.0 * (record.ended_at - record.created_at), abs=1.0)
            await sub.delete()
            return str(job.Id)

    job = cell.job(asyncio.run(go()))
    assert job.state == "succeeded", job.error_message
    pick = job.result
    assert isinstance(pick, PickResult) and pick.place is not None
    placed = part_at(truth_parts(served.http), pick.place.T_base_part_goal.T())
    assert len(placed) == 1 and not placed[0]["held"]
    settled_tcp(cell)


def test_an_applied_calibration_becomes_the_active_configuration(served: Served) -> None:
    """A hand-eye routine applied to the running cell is the configuration a client reads at
    once (no job needed to refresh it): its job id and when it was applied;
    ``GetConfigurationById`` answers it and the file's ``config`` is no longer there."""
    cell, http = served.cell, served.http
    assert cell.home("test", speed_deg_s=120.0, wait=True).state == "succeeded"
    place_parts(http, [(0.0, 0.0)], 0.0, T_base_origin=served.T_base_home_target)
    r = http.post(HAND_EYE, json={"views": 6, "speed_mm_s": 400}, headers=AUTH["operator"])
    assert r.status_code == 200, r.text
    job_id = r.json()["id"]
    job = wait_job(http, job_id, 120.0, url=HAND_EYE)
    assert job["state"] == "succeeded", job["error"]
    r = http.post(f"{HAND_EYE}/{job_id}/apply", json={},
                  headers=AUTH["operator"])
    assert r.status_code == 200, r.text
    applied_s = time.time()

    async def go() -> None:
        async with opc_client(served.url, "plc") as c:
            await c.load_data_type_definitions()
            mv = await c.get_namespace_index(URI)
            configs = (await _check_instance(await _instance(c, mv), mv))[
                "ConfigurationManagement"]
            active = await configs.get_child(f"{mv}:ActiveConfiguration")
            deadline = time.monotonic() + 10.0
            while (config := await active.read_value()).InternalId.Id != job_id:
                assert time.monotonic() < deadline, config
                await asyncio.sleep(0.1)
            assert config.LastModified.timestamp() == pytest.approx(applied_s, abs=5.0)
            _, by_id, error = await configs.call_method(
                f"{mv}:GetConfigurationById", ua.ConfigurationIdDataType(Id=job_id),
                ua.Variant(0, ua.VariantType.Int32))
            assert error == 0 and by_id.InternalId.Id == job_id
            *_, error = await configs.call_method(
                f"{mv}:GetConfigurationById", ua.ConfigurationIdDataType(Id="config"),
                ua.Variant(0, ua.VariantType.Int32))
            assert error != 0

    asyncio.run(go())
    settled_tcp(cell)
