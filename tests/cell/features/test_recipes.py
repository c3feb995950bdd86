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
from tests.support.waiting import wait_until


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

    from api.plc.xmlrpc import XmlRpcServer
    from estimator.transforms import T_from_ur_pose

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = int(s.getsockname()[1])
    config = sim_config(tmp_path, urscript={"xmlrpc_port": port})
    with running_cell(config) as cell:
        cell.recipes.save(parse_spec(spec(config, number=4, standoff_mm=80.0)), "test")
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


def four_dots(config: Any, **target: Any) -> dict[str, Any]:
    """A recipe whose layout is four of the simulated plate's six dots."""
    out = spec(config, number=7, name="plate-4")
    out["targets"][0]["points_mm"] = out["targets"][0]["points_mm"][:4]
    out["targets"][0].update(target)
    return out


def located_dots(http: TestClient) -> int:
    r = http.post("/api/v1/locate", json={}, headers=AUTH["plc"])
    assert r.status_code == 200, r.text
    return int(r.json()["quality"]["n_points"])


def test_a_recipe_layout_is_looked_for_during_its_job_only(tmp_path: Path) -> None:
    config = sim_config(tmp_path, approach={"speed_mm_s": 250.0, "accel_mm_s2": 1200.0})
    # a recipe saved before the speed limits were what they are now: its jobs are refused
    RecipeStore(tmp_path / "recipes.json").save(
        parse_spec(four_dots(config, speed_mm_s=1e9)), "op")
    six = len(config.target.points_mm)
    with running_cell(config) as cell, TestClient(create_app(cell)) as http:
        layout = cell.core.locator.target
        assert located_dots(http) == six
        last = cell.core.locator.last
        r = http.post("/api/v1/recipes/plate-4/approach", json={}, headers=AUTH["plc"])
        assert r.status_code == 422 and r.json()["error"]["code"] == "speed_limit", r.text
        assert not cell.commanded()
        assert cell.core.locator.target is layout and cell.core.locator.last is last
        assert located_dots(http) == six
        # a recipe the cell can run: its layout while its job runs, the cell's again after
        r = http.put("/api/v1/recipes", json=four_dots(config, speed_mm_s=200.0),
                     headers=AUTH["operator"])
        assert r.status_code == 200, r.text
        r = http.post("/api/v1/recipes/plate-4/approach", json={}, headers=AUTH["plc"])
        assert r.status_code == 200, r.text
        assert len(cell.core.locator.target.points_mm) == 4  # while the job runs
        wait_until(lambda: cell.job(r.json()["id"]).finished, 60, "the recipe's approach")
        assert cell.job(r.json()["id"]).state == "succeeded"
        assert cell.core.locator.target is layout
        assert located_dots(http) == six
        # wait: as /approach, the answer is the ended job
        r = http.post("/api/v1/recipes/plate-4/approach", json={"wait": True},
                      headers=AUTH["plc"])
        assert r.status_code == 200, r.text
        job = r.json()
        assert job["state"] == "succeeded", job["error"]
        assert job["params"]["recipe"]["version"] == 2
        assert cell.core.locator.target is layout
        assert located_dots(http) == six


def test_recipes_are_checked_when_saved_by_the_approachs_rules(tmp_path: Path) -> None:
    from api import remote
    from api.remote import RemoteCaller

    config = sim_config(tmp_path)
    with running_cell(config) as cell, TestClient(create_app(cell)) as http:
        def put(**target: Any) -> Any:
            body = spec(config)
            body["targets"][0].update(target)
            return http.put("/api/v1/recipes", json=body, headers=AUTH["operator"])

        for target, code, field in (
                ({"speed_mm_s": 1e9}, "speed_limit", "targets.0.speed_mm_s"),
                ({"speed_mm_s": 0.01}, "speed_limit", "targets.0.speed_mm_s"),
                ({"standoff_mm": 1e308}, "invalid_standoff", "targets.0.standoff_mm"),
                ({"standoff_mm": "50"}, "invalid_request", "targets.0.standoff_mm"),
                ({"speed_mm_s": True}, "invalid_request", "targets.0.speed_mm_s"),
                ({"dot_diameter_mm": "10"}, "invalid_request", "targets.0.dot_diameter_mm")):
            r = put(**target)
            assert r.status_code == 422, (target, r.text)
            assert r.json()["error"]["code"] == code, (target, r.text)
            assert field in r.json()["error"]["message"], (target, r.text)
        assert http.get("/api/v1/recipes", headers=AUTH["viewer"]).json()["recipes"] == []
        r = http.put("/api/v1/recipes", json={**spec(config), "number": True},
                     headers=AUTH["operator"])
        assert r.status_code == 422 and "number" in r.json()["error"]["message"], r.text
        assert put().status_code == 200
        # one standoff rule for /approach and a recipe's approach, whatever the door
        for path in ("/api/v1/approach", "/api/v1/recipes/plate-a/approach"):
            r = http.post(path, json={"standoff_mm": 1e308}, headers=AUTH["plc"])
            assert r.status_code == 422, r.text
            assert r.json()["error"]["message"].startswith("standoff_mm:"), r.text
        plc = RemoteCaller("opcua", "plc", "plc")
        for start in (lambda: remote.approach(cell, plc, 1e308, ""),
                      lambda: remote.approach_recipe(cell, plc, "plate-a", "", 1e308)):
            with pytest.raises(CellError) as err:
                start()
            assert err.value.code == "invalid_standoff", err.value.message
            assert "standoff_mm" in err.value.message
        r = http.post("/api/v1/recipes/plate-a/approach", json={"speed_mm_s": 1000},
                      headers=AUTH["plc"])
        assert r.status_code == 422 and r.json()["error"]["code"] == "speed_limit", r.text
        assert "speed_mm_s" in r.json()["error"]["message"]
        assert not cell.commanded()


def test_a_pick_recipe_names_its_place_and_a_place_without_a_pick_is_refused(
        tmp_path: Path) -> None:
    config = sim_config(tmp_path)
    store = RecipeStore(tmp_path / "recipes.json")
    data = spec(config)
    assert parse_spec(data).targets[0].job == "approach"  # what recipes did before
    data["targets"][0].update(job="pick", place="tray-1")
    saved = store.save(parse_spec(data), "test")
    again = RecipeStore(tmp_path / "recipes.json").get(saved.name).target()
    assert (again.job, again.place) == ("pick", "tray-1")
    del data["targets"][0]["job"]
    with pytest.raises(CellError) as refused:
        parse_spec(data)
    assert refused.value.code == "invalid_recipe" and "targets.0" in refused.value.message
    data["targets"][0].update(job="weld", place="")
    with pytest.raises(CellError):
        parse_spec(data)
