"""The OPC UA server seen by a client on another stack (node-opcua, driven by
``tests/support/clients/node_opcua_jobs.js``): right after Approach returns, JobId/JobKind/JobState
already hold the new running job, 100 times of 100; every job's end comes with its result
(carrying the JobId) and as a JobEnded event. Also, with asyncua as the PLC: the Machine
Vision subset (state machine, recipes, StartSingleJob, StartContinuousJob as tracking, results
with ids, the mode and recipe kept over a restart).

node-opcua is installed with npm into ``$NODE_OPCUA_DIR`` (default
``~/.cache/ur-vision-cell/node-opcua``, outside the repository) the first time; without node
or npm the node-opcua test is skipped."""

from __future__ import annotations

import asyncio
import contextlib
import json
import os
import shutil
import subprocess
import time
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import pytest

from api.plc.opcua import OpcUaServer
from cell.config.endpoints import opcua_cert_dir
from cell.config.schema import CellConfig
from cell.service import Cell
from cell.vision.frames import approach_tcp
from estimator.transforms import T_from_pose_dict, pose_distance
from tests.support.cell import running_cell, settled_tcp, sim_config
from tests.support.net import free_port
from tests.support.opcua import opc_client
from tests.support.paths import REPO

SCRIPT = REPO / "tests" / "support" / "clients" / "node_opcua_jobs.js"
N_CALLS = 100


@dataclass
class Served:
    cell: Cell
    url: str


@pytest.fixture
def served(tmp_path: Path) -> Iterator[Served]:
    port = free_port()
    config = sim_config(tmp_path, approach={"speed_mm_s": 250.0, "accel_mm_s2": 1200.0},
                        opcua={"endpoint": f"opc.tcp://127.0.0.1:{port}"})
    with running_cell(config) as cell:
        server = OpcUaServer(cell, config.opcua, opcua_cert_dir(config))
        server.start()
        try:
            yield Served(cell, f"opc.tcp://127.0.0.1:{port}")
        finally:
            server.close()


def node_opcua() -> Path:
    """The folder whose node_modules holds node-opcua (installed there once)."""
    if shutil.which("node") is None or shutil.which("npm") is None:
        pytest.skip("node and npm are needed for the node-opcua client")
    folder = Path(os.environ.get("NODE_OPCUA_DIR")
                  or Path.home() / ".cache" / "ur-vision-cell" / "node-opcua")
    if not (folder / "node_modules" / "node-opcua").is_dir():
        folder.mkdir(parents=True, exist_ok=True)
        done = subprocess.run(["npm", "install", "--prefix", str(folder), "--no-audit",
                               "--no-fund", "node-opcua"], capture_output=True, text=True,
                              timeout=600, check=False)
        if done.returncode != 0:
            pytest.skip(f"npm could not install node-opcua: {done.stderr[-300:]}")
    return folder


def test_node_opcua_reads_the_new_job_at_once_100_of_100(served: Served) -> None:
    folder = node_opcua()
    env = {**os.environ, "NODE_PATH": str(folder / "node_modules")}
    done = subprocess.run(["node", str(SCRIPT), served.url, "plc", "sim-plc", str(N_CALLS)],
                          capture_output=True, text=True, timeout=900, env=env, check=False)
    assert done.returncode == 0, done.stderr[-2000:]
    out = json.loads(done.stdout.strip().splitlines()[-1])
    assert out["mismatches"] == [], out["mismatches"][:5]
    assert out["consistent"] == N_CALLS
    assert out["events"] == N_CALLS  # one JobEnded event per job, with its id and state
    jobs = served.cell.jobs.list_jobs(N_CALLS)
    assert len(jobs) == N_CALLS and all(j.finished for j in jobs)
    assert out["cancelled"] == sum(j.state == "cancelled" for j in jobs)


def test_machine_vision_single_job_with_a_recipe(served: Served) -> None:
    cell = served.cell
    t = cell.config.target
    content = json.dumps({"targets": [{
        "name": "plate", "points_mm": [list(p) for p in t.points_mm],
        "dot_diameter_mm": t.dot_diameter_mm, "polarity": t.polarity, "standoff_mm": 45.0}]})

    async def go() -> None:
        async with opc_client(served.url, "operator") as op, \
                opc_client(served.url, "plc") as plc:
            ns = await plc.get_namespace_index("urn:ur-vision-cell")
            objects = plc.nodes.objects
            vs = await objects.get_child(f"{ns}:VisionSystem")
            sm = await vs.get_child(f"{ns}:VisionStateMachine")
            auto = await sm.get_child(f"{ns}:VisionAutomaticModeStateMachine")
            recipes = await vs.get_child(f"{ns}:RecipeManagement")
            results = await vs.get_child(f"{ns}:ResultManagement")
            state = await sm.get_child(f"{ns}:CurrentState")
            sub_state = await auto.get_child(f"{ns}:CurrentState")
            assert (await state.read_value()).Text == "Preoperational"

            # a PLC may not add recipes; an operator may; the PLC prepares one by number
            r_recipes = plc.get_node(recipes.nodeid)
            out = await r_recipes.call_method(f"{ns}:AddRecipe", "plate-a", "7", content)
            assert out[-1] != 0  # forbidden for the plc role
            op_recipes = op.get_node(recipes.nodeid)
            out = await op_recipes.call_method(f"{ns}:AddRecipe", "plate-a", "7", content)
            assert out == ["plate-a@1", 0], out
            assert (await r_recipes.call_method(f"{ns}:GetRecipeListFiltered"))[0] == \
                ["plate-a@1"]
            # a single job before automatic mode is refused, then runs
            out = await auto.call_method(f"{ns}:StartSingleJob", "m1", "p1", "7", "prod")
            assert out[0] == "" and out[1] != 0
            assert await sm.call_method(f"{ns}:SelectModeAutomatic") == 0
            assert (await sub_state.read_value()).Text == "Initialized"
            assert (await r_recipes.call_method(f"{ns}:PrepareRecipe", "7")) == ["plate-a@1", 0]
            assert (await sub_state.read_value()).Text == "Ready"
            job_id, error = await auto.call_method(f"{ns}:StartSingleJob", "m1", "p1", "", "")
            assert error == 0 and job_id
            cell_obj = await objects.get_child(f"{ns}:Cell")
            assert await (await cell_obj.get_child(f"{ns}:JobId")).read_value() == job_id
            assert await (await cell_obj.get_child(f"{ns}:JobState")).read_value() == "running"
            assert (await sub_state.read_value()).Text == "SingleExecution"
            result_job = await results.get_child(f"{ns}:JobId")
            deadline = time.monotonic() + 60
            while await result_job.read_value() != job_id:
                assert time.monotonic() < deadline, "no result for the single job"
                await asyncio.sleep(0.05)
            result_id = await (await results.get_child(f"{ns}:ResultId")).read_value()
            assert result_id == f"r-{job_id}"
            body, error = await results.call_method(f"{ns}:GetResultById", result_id)
            assert error == 0
            r = json.loads(body)
            assert r["job_id"] == job_id and r["state"] == "succeeded"
            assert r["recipe"] == {"name": "plate-a", "number": 7, "version": 1,
                                   "target": "plate"}
            assert cell.sim is not None
            d_mm, _ = pose_distance(T_from_pose_dict(r["located"]),
                                    cell.sim.true_T_base_target())
            assert d_mm < 1.0
            assert (await sub_state.read_value()).Text == "Ready"
            job = cell.job(job_id)
            assert job.params["recipe"]["version"] == 1 and job.params["standoff_mm"] == 45.0
            # Halt stops and halts; Reset back to Preoperational
            assert await sm.call_method(f"{ns}:Halt") == 0
            assert (await state.read_value()).Text == "Halted"
            out = await auto.call_method(f"{ns}:StartSingleJob", "m2", "p2", "", "")
            assert out[1] != 0
            assert await plc.get_node(sm.nodeid).call_method(f"{ns}:Reset") != 0  # recover
            assert await op.get_node(sm.nodeid).call_method(f"{ns}:Reset") == 0
            assert (await state.read_value()).Text == "Preoperational"
            _, error = await results.call_method(f"{ns}:GetResultById", "r-nothing")
            assert error != 0

    asyncio.run(go())
    settled_tcp(cell)


async def _vision(client: Any) -> dict[str, Any]:
    """The Machine Vision nodes a PLC uses, by browse name."""
    ns = await client.get_namespace_index("urn:ur-vision-cell")
    vs = await client.nodes.objects.get_child(f"{ns}:VisionSystem")
    sm = await vs.get_child(f"{ns}:VisionStateMachine")
    auto = await sm.get_child(f"{ns}:VisionAutomaticModeStateMachine")
    recipes = await vs.get_child(f"{ns}:RecipeManagement")
    return {"ns": ns, "sm": sm, "auto": auto, "recipes": recipes,
            "results": await vs.get_child(f"{ns}:ResultManagement"),
            "state": await sm.get_child(f"{ns}:CurrentState"),
            "sub_state": await auto.get_child(f"{ns}:CurrentState"),
            "prepared": await recipes.get_child(f"{ns}:PreparedRecipe")}


async def _text_becomes(node: Any, text: str, timeout_s: float) -> None:
    deadline = time.monotonic() + timeout_s
    while (await node.read_value()).Text != text:
        assert time.monotonic() < deadline, f"not {text} after {timeout_s} s"
        await asyncio.sleep(0.05)


def _recipe_content(cell: Cell, standoff_mm: float, dot_diameter_mm: float | None = None
                    ) -> str:
    t = cell.config.target
    return json.dumps({"targets": [{
        "name": "plate", "points_mm": [list(p) for p in t.points_mm],
        "dot_diameter_mm": dot_diameter_mm or t.dot_diameter_mm, "polarity": t.polarity,
        "standoff_mm": standoff_mm}]})


@contextlib.contextmanager
def _service(config: CellConfig) -> Iterator[Cell]:
    """The cell and its OPC UA server, as ``cell serve`` runs them."""
    with running_cell(config) as cell:
        server = OpcUaServer(cell, config.opcua, opcua_cert_dir(config))
        server.start()
        try:
            yield cell
        finally:
            server.close()


def test_machine_vision_continuous_job_tracks_until_stop(tmp_path: Path) -> None:
    """StartContinuousJob is tracking with the prepared recipe: ContinuousExecution while the
    track job runs (the arm held at the recipe's standoff from the true target), a single job
    meanwhile refused as busy, Stop ends it and the state machine is Ready again, with the
    job's result (cancelled, recipe and version) under its id. The target may go unseen for
    1 s here (0.1 s by default): a loaded shared test host must not end the tracking."""
    port = free_port()
    config = sim_config(tmp_path, opcua={"endpoint": f"opc.tcp://127.0.0.1:{port}"},
                        servo={"lost_after_s": 1.0})
    with _service(config) as cell:
        _continuous_job(cell, f"opc.tcp://127.0.0.1:{port}")


def _continuous_job(cell: Cell, url: str) -> None:

    async def go() -> None:
        async with opc_client(url, "operator") as op, opc_client(url, "plc") as plc:
            mv = await _vision(plc)
            ns, auto = mv["ns"], mv["auto"]
            op_recipes = op.get_node(mv["recipes"].nodeid)
            out = await op_recipes.call_method(f"{ns}:AddRecipe", "plate-c", "9",
                                               _recipe_content(cell, 70.0))
            assert out == ["plate-c@1", 0], out
            assert await mv["sm"].call_method(f"{ns}:SelectModeAutomatic") == 0
            job_id, error = await auto.call_method(
                f"{ns}:StartContinuousJob", "m1", "p1", "9", "prod")
            assert error == 0 and job_id
            assert (await mv["sub_state"].read_value()).Text == "ContinuousExecution"
            job = cell.job(job_id)
            assert job.kind == "track" and job.state == "running"
            assert job.params["recipe"] == {"name": "plate-c", "number": 9, "version": 1,
                                            "target": "plate"}
            assert job.params["standoff_mm"] == 70.0
            assert job.params["duration_s"] == cell.config.servo.max_track_s
            # holding the standoff pose on the target (simulated truth, not the cell's view)
            assert cell.sim is not None
            goal = approach_tcp(cell.sim.true_T_base_target(),
                                cell.config.approach.T_target_tcp.T(), 70.0)
            deadline = time.monotonic() + 60
            while pose_distance(cell.sim.true_T_base_tcp(), goal)[0] > 2.0:
                assert time.monotonic() < deadline, "tracking did not reach the standoff"
                assert cell.job(job_id).state == "running", cell.job(job_id).error_message
                await asyncio.sleep(0.1)
            out = await auto.call_method(
                f"{ns}:StartSingleJob", "m2", "p2", "", "")
            assert out[0] == "" and out[1] == 3  # busy
            assert cell.job(job_id).state == "running"  # the refusal changed nothing
            assert await auto.call_method(f"{ns}:Stop") == 0
            await _text_becomes(mv["sub_state"], "Ready", 30)
            assert cell.job(job_id).state == "cancelled"
            body, error = await mv["results"].call_method(
                f"{ns}:GetResultById", f"r-{job_id}")
            assert error == 0
            r = json.loads(body)
            assert r["state"] == "cancelled" and r["recipe"]["name"] == "plate-c"
            assert (await mv["state"].read_value()).Text == "Operational"

    asyncio.run(go())
    settled_tcp(cell)


def test_machine_vision_mode_and_recipe_survive_a_restart(tmp_path: Path) -> None:
    """After a restart of the service (cell and OPC UA server) on the same state dir, the
    remembered recipe is prepared again (its layout is the locator's) and automatic mode
    resumes: Operational/Ready. After a Halt the next start stays Preoperational (recipe
    still prepared); an unreadable memory file starts Preoperational with nothing prepared."""
    port = free_port()
    config = sim_config(tmp_path, opcua={"endpoint": f"opc.tcp://127.0.0.1:{port}"})
    url = f"opc.tcp://127.0.0.1:{port}"

    def service() -> contextlib.AbstractContextManager[Cell]:
        return _service(config)

    async def states() -> tuple[str, str, str]:
        async with opc_client(url, "plc") as plc:
            mv = await _vision(plc)
            return ((await mv["state"].read_value()).Text,
                    (await mv["sub_state"].read_value()).Text,
                    await mv["prepared"].read_value())

    recipe_dot_mm = config.target.dot_diameter_mm + 1.5  # tells its layout from the config's

    async def set_up(cell: Cell) -> None:
        async with opc_client(url, "operator") as op:
            mv = await _vision(op)
            ns = mv["ns"]
            out = await mv["recipes"].call_method(
                f"{ns}:AddRecipe", "plate-r", "11", _recipe_content(cell, 50.0, recipe_dot_mm))
            assert out == ["plate-r@1", 0], out
            assert await mv["sm"].call_method(f"{ns}:SelectModeAutomatic") == 0
            assert (await mv["recipes"].call_method(
                f"{ns}:PrepareRecipe", "plate-r")) == ["plate-r@1", 0]

    async def halt() -> None:
        async with opc_client(url, "operator") as op:
            mv = await _vision(op)
            assert await mv["sm"].call_method(f"{mv['ns']}:Halt") == 0

    with service() as cell:
        assert asyncio.run(states()) == ("Preoperational", "", "")
        asyncio.run(set_up(cell))
        assert asyncio.run(states()) == ("Operational", "Ready", "plate-r")
    assert json.loads((tmp_path / "machine_vision.json").read_text()) == {
        "automatic": True, "prepared": "plate-r"}

    with service() as cell:
        assert asyncio.run(states()) == ("Operational", "Ready", "plate-r")
        assert cell.core.locator.target.dot_diameter_mm == recipe_dot_mm
        asyncio.run(halt())
    with service() as cell:
        assert asyncio.run(states()) == ("Preoperational", "", "plate-r")
        assert cell.core.locator.target.dot_diameter_mm == recipe_dot_mm

    (tmp_path / "machine_vision.json").write_text("{not json")
    with service() as cell:
        assert asyncio.run(states()) == ("Preoperational", "", "")
        assert cell.core.locator.target.dot_diameter_mm == config.target.dot_diameter_mm
