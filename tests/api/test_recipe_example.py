"""docs/plc.md's example body for ``PUT /api/v1/recipes``, sent as the doc has it: an operator
saves it, a PLC may not, and the PLC approaches with it. The audit log and the recipe's
``saved_by`` name the caller in the one format every door uses, ``http:<name>(<role>)``."""

from __future__ import annotations

import json
import re
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
from fastapi.testclient import TestClient

from api.app import create_app
from cell.service import Cell
from tests.support.cell import AUTH, running_cell, sim_config
from tests.support.jobs import wait_job

ROOT = Path(__file__).resolve().parents[2]


def doc_example() -> dict[str, Any]:
    """The first json block after the "Saving a recipe over HTTP" heading of docs/plc.md."""
    text = (ROOT / "docs" / "plc.md").read_text()
    section = text.split("### Saving a recipe over HTTP", 1)[1]
    match = re.search(r"```json\n(.*?)\n```", section, re.DOTALL)
    assert match, "no json example under the heading"
    body: dict[str, Any] = json.loads(match.group(1))
    return body


@pytest.fixture
def client(tmp_path: Path) -> Iterator[TestClient]:
    config = sim_config(tmp_path, approach={"speed_mm_s": 250.0, "accel_mm_s2": 1200.0})
    with running_cell(config) as cell, TestClient(create_app(cell)) as c:
        yield c


def test_the_documented_recipe_body_saves_and_approaches(client: TestClient) -> None:
    cell: Cell = client.app.state.cell  # type: ignore[attr-defined]
    body = doc_example()
    assert client.put("/api/v1/recipes", json=body, headers=AUTH["plc"]).status_code == 403
    r = client.put("/api/v1/recipes", json=body, headers=AUTH["operator"])
    assert r.status_code == 200, r.text
    saved = r.json()
    assert saved["version"] == 1 and saved["saved_by"] == "http:operator(operator)"
    # every documented value saved as sent (the fields it leaves out take their defaults)
    assert {k: saved[k] for k in body if k != "targets"} == \
        {k: v for k, v in body.items() if k != "targets"}
    assert [{k: t[k] for k in sent} for t, sent in zip(saved["targets"], body["targets"],
                                                        strict=True)] == body["targets"]
    # the doc's approach: the PLC, with the recipe's target
    r = client.post(f"/api/v1/recipes/{body['name']}/approach",
                    json={"target": "main", "standoff_mm": None}, headers=AUTH["plc"])
    assert r.status_code == 200, r.text
    job = wait_job(client, r.json()["id"], 60.0)
    assert job["state"] == "succeeded", job
    assert job["params"]["recipe"] == {"name": body["name"], "number": body["number"],
                                       "version": 1, "target": "main"}
    # one caller format: every HTTP audit row, the recipe's saved_by and the job's caller
    rows = [(e.caller, e.command, e.outcome) for e in cell.jobs.audit_log(100)]
    assert ("http:operator(operator)", "save_recipe", "ok") in rows, rows
    assert ("http:plc(plc)", "save_recipe", "refused:forbidden") in rows, rows
    assert job["caller"] == "http:plc(plc)"
    assert all(re.fullmatch(r"(http|opcua|modbus|xmlrpc):[\w.-]+\(\w+\)|anonymous", c)
               for c, _, _ in rows if c.startswith(("http", "plc", "operator", "viewer"))), rows
