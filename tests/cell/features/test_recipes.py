"""Recipes: versioned storage that survives a restart, typed refusals that change nothing,
and the HTTP routes (save as operator, refused for a PLC, an approach with a recipe whose job
records the recipe and version and ends at the recipe's standoff against the simulated truth)."""

from __future__ import annotations

import json
import time
from pathlib import Path
from typing import Any

import pytest
from fastapi.testclient import TestClient

from api.app import create_app
from cell.errors import CellError
from cell.features.recipes import RecipeStore, parse_spec
from cell.vision.frames import approach_tcp
from estimator.transforms import pose_distance
from tests.support.cell import AUTH, running_cell, settled_tcp, sim_config


def spec(config: Any, number: int = 1, standoff_mm: float = 50.0,
         name: str = "plate-a") -> dict[str, Any]:
    t = config.target
    return {"name": name, "number": number, "targets": [{
        "name": "main", "points_mm": [list(p) for p in t.points_mm],
        "dot_diameter_mm": t.dot_diameter_mm, "polarity": t.polarity,
        "standoff_mm": standoff_mm}]}


def test_versions_survive_a_restart_and_refusals_change_nothing(tmp_path: Path) -> None:
    config = sim_config(tmp_path)
    store = RecipeStore(tmp_path / "recipes.json")
    assert store.save(parse_spec(spec(config)), "op").version == 1
    assert store.save(parse_spec(spec(config, standoff_mm=70.0)), "op").version == 2
    again = RecipeStore(tmp_path / "recipes.json")
    assert [r.version for r in again.versions("plate-a")] == [1, 2]
    assert again.get(1).targets[0].standoff_mm == 70.0
    assert again.get("plate-a", 1).targets[0].standoff_mm == 50.0
    before = (tmp_path / "recipes.json").read_text()
    with pytest.raises(CellError) as err:
        again.save(parse_spec(spec(config, number=1, name="other")), "op")
    assert err.value.code == "recipe_number_taken"
    bad = spec(config)
    bad["targets"][0]["points_mm"] = [[0, 0, 0]] * 4
    with pytest.raises(CellError) as err:
        parse_spec(bad)
    assert err.value.code == "invalid_recipe"
    with pytest.raises(CellError) as err:
        again.get(9)
    assert err.value.code == "recipe_not_found"
    assert (tmp_path / "recipes.json").read_text() == before
    (tmp_path / "recipes.json").write_text("{not json")
    broken = RecipeStore(tmp_path / "recipes.json")
    with pytest.raises(CellError) as err:
        broken.list()
    assert err.value.code == "recipe_store_unreadable"


def test_http_recipes_and_an_approach_with_one(tmp_path: Path) -> None:
    config = sim_config(tmp_path, approach={"speed_mm_s": 250.0, "accel_mm_s2": 1200.0})
    with running_cell(config) as cell, TestClient(create_app(cell)) as http:
        r = http.put("/api/v1/recipes", json=spec(config), headers=AUTH["plc"])
        assert r.status_code == 403, r.text
        r = http.put("/api/v1/recipes", json=spec(config, standoff_mm=55.0),
                     headers=AUTH["operator"])
        assert r.status_code == 200 and r.json()["version"] == 1, r.text
        r = http.put("/api/v1/recipes", json=spec(config, standoff_mm=65.0),
                     headers=AUTH["operator"])
        assert r.json()["version"] == 2
        assert [x["version"] for x in http.get(
            "/api/v1/recipes/plate-a", headers=AUTH["viewer"]).json()["versions"]] == [1, 2]
        r = http.post("/api/v1/recipes/nope/approach", json={}, headers=AUTH["plc"])
        assert r.status_code == 404 and r.json()["error"]["code"] == "recipe_not_found"
        assert not cell.commanded()
        r = http.post("/api/v1/recipes/1/approach", json={}, headers=AUTH["plc"])
        assert r.status_code == 200, r.text
        job_id = r.json()["id"]
        assert r.json()["params"]["recipe"] == {"name": "plate-a", "number": 1, "version": 2,
                                                "target": "main"}
        for _ in range(600):
            job = cell.job(job_id)
            if job.finished:
                break
            time.sleep(0.1)
        assert job.state == "succeeded", job.error_message
        assert cell.sim is not None
        goal = approach_tcp(cell.sim.true_T_base_target(), config.approach.T_target_tcp.T(),
                            65.0)
        d_mm, _ = pose_distance(settled_tcp(cell), goal)
        assert d_mm < 1.5, d_mm
        assert json.loads(json.dumps(job.params))["standoff_mm"] == 65.0


def test_xmlrpc_recipe_pose_is_the_goal_for_the_recipes_standoff(tmp_path: Path) -> None:
    import socket
    import xmlrpc.client

    from api import remote
    from api.plc.xmlrpc import XmlRpcServer
    from estimator.transforms import T_from_ur_pose

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = int(s.getsockname()[1])
    config = sim_config(tmp_path, urscript={"xmlrpc_port": port})
    with running_cell(config) as cell:
        remote.recipe_store(cell).save(parse_spec(spec(config, number=4, standoff_mm=80.0)),
                                       "test")
        server = XmlRpcServer(cell, config.urscript)
        server.start()
        try:
            rpc = xmlrpc.client.ServerProxy(f"http://127.0.0.1:{port}/RPC2")
            p = rpc.recipe_pose(4)
            assert cell.sim is not None
            goal = approach_tcp(cell.sim.true_T_base_target(),
                                config.approach.T_target_tcp.T(), 80.0)
            T = T_from_ur_pose([p[k] for k in ("x", "y", "z", "rx", "ry", "rz")])
            assert pose_distance(T, goal)[0] < 1.0
            with pytest.raises(xmlrpc.client.Fault) as err:
                rpc.recipe_pose("nope")
            assert err.value.faultString.startswith("recipe_not_found")
            assert not cell.commanded()
        finally:
            server.close()
