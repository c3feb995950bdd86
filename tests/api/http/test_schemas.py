"""Request bodies parse strictly: a string or a boolean for a number, a number or a string for
a flag is refused with 422 naming the field, and nothing moves; an integer for a float is
fine. Checked against the simulated truth (the arm and the target stay where they were)."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import pytest
from fastapi.testclient import TestClient

from api.app import create_app
from cell.service import Cell
from estimator.transforms import pose_distance
from tests.support.cell import AUTH, running_cell, settled_tcp, sim_config, tcp, world


@pytest.fixture
def served(tmp_path: Path) -> Any:
    with running_cell(sim_config(tmp_path)) as cell, TestClient(create_app(cell)) as http:
        yield cell, http


def refused(http: TestClient, method: str, path: str, body: dict[str, Any], field: str,
            role: str = "operator") -> None:
    r = http.request(method, path, json=body, headers=AUTH[role])
    assert r.status_code == 422, (path, body, r.text)
    error = r.json()["error"]
    assert error["code"] == "invalid_request", error
    assert error["message"].startswith(field + ":") or f"; {field}:" in error["message"], \
        (field, error)


def still(cell: Cell, before: np.ndarray) -> None:
    assert not cell.commanded()
    assert pose_distance(tcp(cell), before)[0] < 0.01


def test_motion_bodies_refuse_strings_and_booleans_for_numbers_and_flags(
        served: tuple[Cell, TestClient]) -> None:
    cell, http = served
    before = settled_tcp(cell)
    refused(http, "POST", "/api/v1/approach", {"standoff_mm": 40, "wait": "yes"}, "wait",
            "plc")
    refused(http, "POST", "/api/v1/approach", {"standoff_mm": 40, "wait": 1}, "wait", "plc")
    refused(http, "POST", "/api/v1/approach", {"standoff_mm": "40"}, "standoff_mm", "plc")
    refused(http, "POST", "/api/v1/approach", {"standoff_mm": True}, "standoff_mm", "plc")
    refused(http, "POST", "/api/v1/approach", {"use_last_locate": "true"}, "use_last_locate",
            "plc")
    step = {"mode": "step", "frame": "base", "translation_mm": [0, 0, "10"]}
    refused(http, "POST", "/api/v1/jog", step, "step.translation_mm.2")
    refused(http, "POST", "/api/v1/jog", {**step, "translation_mm": [0, 0, True]},
            "step.translation_mm.2")
    refused(http, "POST", "/api/v1/jog", {**step, "translation_mm": [0, 0, 0],
                                          "speed_mm_s": "50"}, "step.speed_mm_s")
    refused(http, "POST", "/api/v1/jog", {"mode": "continuous", "linear_mm_s": [0, "5", 0]},
            "continuous.linear_mm_s.1")
    refused(http, "POST", "/api/v1/track", {"standoff_mm": 40, "duration_s": 1, "wait": 0},
            "wait")
    refused(http, "POST", "/api/v1/arm/home", {"wait": "false"}, "wait")
    refused(http, "POST", "/api/v1/arm/power", {"on": 1}, "on")
    refused(http, "POST", "/api/v1/locate", {"n_frames": "2"}, "n_frames")
    still(cell, before)
    # an integer where a float is expected is a number: the step moves 10 mm up
    r = http.post("/api/v1/jog", json={"mode": "step", "frame": "base",
                                       "translation_mm": [0, 0, 10]}, headers=AUTH["operator"])
    assert r.status_code == 200, r.text
    moved = settled_tcp(cell)
    assert abs(moved[2, 3] - before[2, 3] - 10.0) < 0.5


def test_sim_target_refuses_a_boolean_in_a_number_vector(
        served: tuple[Cell, TestClient]) -> None:
    cell, http = served
    target = world(cell).true_T_base_target()
    body = {"position_mm": [-480, -130, False], "rotvec_rad": [0, 0, 0]}
    refused(http, "PUT", "/api/v1/sim/target", body, "position_mm.2")
    refused(http, "PUT", "/api/v1/sim/target", {"position_mm": [-480, -130, 0],
                                                "rotvec_rad": [0, 0, 0],
                                                "velocity_mm_s": [0, "1", 0]},
            "velocity_mm_s.1")
    assert np.array_equal(world(cell).true_T_base_target(), target)


def test_the_schema_still_says_number_and_boolean(served: tuple[Cell, TestClient]) -> None:
    _, http = served
    schemas = http.get("/openapi.json").json()["components"]["schemas"]
    props = schemas["ApproachRequest"]["properties"]
    assert props["wait"]["type"] == "boolean"
    assert {"type": "number", "minimum": 0.0, "maximum": 500.0} in [
        {k: v for k, v in s.items() if k in ("type", "minimum", "maximum")}
        for s in props["standoff_mm"]["anyOf"]]
    step = schemas["JogStep"]["properties"]["translation_mm"]
    assert [item["type"] for item in step["prefixItems"]] == ["number"] * 3
    # a recipe's bounds are the ones it is checked against when saved
    target = schemas["RecipeTarget"]["properties"]
    assert (target["speed_mm_s"]["minimum"], target["speed_mm_s"]["maximum"]) == (1.0, 250.0)
    assert target["standoff_mm"]["maximum"] == 500.0
