"""The OPC UA server seen by a client on another stack (node-opcua, driven by
``tests/clients/node_opcua_jobs.js``): right after Approach returns, JobId/JobKind/JobState
already hold the new running job, 100 times of 100; every job's end comes with its result
(carrying the JobId) and as a JobEnded event. Also, with asyncua as the PLC: the Machine
Vision subset (state machine, recipes, StartSingleJob, results with ids).

node-opcua is installed with npm into ``$NODE_OPCUA_DIR`` (default
``~/.cache/ur-vision-cell/node-opcua``, outside the repository) the first time; without node
or npm the node-opcua test is skipped."""

from __future__ import annotations

import asyncio
import json
import os
import shutil
import socket
import subprocess
import time
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import pytest

from api.opcua import OpcUaServer
from cell.endpoints import opcua_cert_dir
from cell.service import Cell
from estimator.transforms import T_from_pose_dict, pose_distance
from tests.cell_testing import running_cell, settled_tcp, sim_config
from tests.opcua_testing import opc_client

SCRIPT = Path(__file__).parent / "clients" / "node_opcua_jobs.js"
N_CALLS = 100


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


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
