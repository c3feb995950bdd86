"""The OpenAPI schema's speed bounds are the configured limits, and a speed
that rounds to nothing on the wire is a limit refusal over HTTP, not a runtime error."""

from __future__ import annotations

from pathlib import Path

from fastapi.testclient import TestClient

from api.app import create_app
from tests.support.cell import AUTH, running_cell, sim_config


def _number(prop: dict) -> dict:
    return next(b for b in prop.get("anyOf", [prop]) if b.get("type") == "number")


def test_schema_speed_bounds_are_the_configured_limits(tmp_path: Path) -> None:
    config = sim_config(tmp_path, limits={"max_speed_mm_s": 180.0, "min_speed_mm_s": 2.0,
                                          "max_jog_speed_mm_s": 40.0})
    with running_cell(config) as cell, TestClient(create_app(cell)) as client:
        schemas = client.get("/openapi.json").json()["components"]["schemas"]
        approach = _number(schemas["ApproachRequest"]["properties"]["speed_mm_s"])
        assert (approach["minimum"], approach["maximum"]) == (2.0, 180.0)
        jog = _number(schemas["JogStep"]["properties"]["speed_mm_s"])
        assert (jog["minimum"], jog["maximum"]) == (2.0, 40.0)
        for speed in (5e-324, 1e-300, 0.005, 181.0):
            r = client.post("/api/v1/approach", json={"speed_mm_s": speed},
                            headers=AUTH["plc"])
            assert r.status_code == 422 and r.json()["error"]["code"] == "speed_limit", r.text
            r = client.post("/api/v1/jog", json={"mode": "step", "translation_mm": [0, 0, 5],
                                                 "speed_mm_s": speed}, headers=AUTH["operator"])
            assert r.status_code == 422, r.text
            assert r.json()["error"]["code"] in ("jog_speed_limit", "invalid_request"), r.text
