"""Roles and permissions: the one table in docs/plc.md is the code's (``api.auth.PERMISSIONS``),
every door asks for permissions by those names, and over HTTP the PLC role runs a production
cycle (home, gripper) but may not teach, calibrate, change recipes or settings, jog, unlock or
power (403, audited, nothing changes)."""

from __future__ import annotations

import re
from collections.abc import Iterator
from pathlib import Path

import pytest
from fastapi.testclient import TestClient

from api.app import create_app
from api.auth import ALWAYS, PERMISSIONS
from cell.service import Cell
from estimator.transforms import pose_distance
from tests.support.cell import AUTH, running_cell, settled_tcp, sim_config

ROOT = Path(__file__).resolve().parents[2]
ROLES = ("viewer", "operator", "plc")
OP, PLC = AUTH["operator"], AUTH["plc"]


def documented_table() -> dict[str, dict[str, bool]]:
    """docs/plc.md's permissions x roles table: permission -> {role: allowed}."""
    text = (ROOT / "docs" / "plc.md").read_text()
    lines = iter(text.splitlines())
    for line in lines:
        if line.startswith("| permission |"):
            header = [c.strip() for c in line.strip("|").split("|")]
            break
    else:
        raise AssertionError("docs/plc.md has no permissions table")
    columns = {role: header.index(role) for role in ROLES}
    table: dict[str, dict[str, bool]] = {}
    next(lines)  # |---|
    for line in lines:
        if not line.startswith("|"):
            break
        cells = [c.strip() for c in line.strip("|").split("|")]
        name = cells[0].strip("`")
        table[name] = {role: cells[i] == "yes" for role, i in columns.items()}
    return table


def used_permissions() -> set[str]:
    """Every permission a door asks for in the source of api/."""
    patterns = (r'\brequire(?:_stream)?\(\s*"(\w+)"',  # HTTP dependencies
                r'\brequire\(\s*[\w.]+,\s*\w+,\s*"(\w+)"',  # api.remote.require
                r'\.may\(\s*"(\w+)"')  # RemoteCaller.may
    used: set[str] = set()
    for path in (ROOT / "api").rglob("*.py"):
        text = path.read_text()
        for pattern in patterns:
            used.update(re.findall(pattern, text))
    return used


def test_the_documented_table_is_the_code_s() -> None:
    table = documented_table()
    granted = {p for perms in PERMISSIONS.values() for p in perms}
    assert set(table) - {"(any caller)"} == granted
    assert {"stop"} == ALWAYS and all(table.pop("(any caller)").values())
    for permission, roles in table.items():
        for role in ROLES:
            assert roles[role] == (permission in PERMISSIONS[role]), (permission, role)


def test_every_door_asks_for_a_known_permission() -> None:
    used = used_permissions()
    known = {p for perms in PERMISSIONS.values() for p in perms} | ALWAYS
    assert used and used <= known, used - known
    # each permission but the reserved pick is asked for by some door
    assert known - used <= {"pick"}, known - used


def test_the_plc_role_covers_a_production_cycle_not_commissioning() -> None:
    plc, operator = PERMISSIONS["plc"], PERMISSIONS["operator"]
    assert {"locate", "approach", "track", "home", "gripper", "pick"} <= plc
    assert not plc & {"teach", "calibrate", "edit_recipes", "camera", "jog", "recover",
                      "sim_write"}
    assert plc <= operator


@pytest.fixture
def client(tmp_path: Path) -> Iterator[TestClient]:
    config = sim_config(tmp_path, gripper="sim")
    with running_cell(config) as cell, TestClient(create_app(cell)) as c:
        yield c


def test_over_http_a_plc_homes_and_grips_but_may_not_commission(client: TestClient) -> None:
    cell: Cell = client.app.state.cell  # type: ignore[attr-defined]
    r = client.post("/api/v1/arm/home", json={"wait": True}, headers=PLC)
    assert r.status_code == 200 and r.json()["state"] == "succeeded", r.text
    for action in ("open", "close", "open"):
        r = client.post("/api/v1/gripper", json={"action": action}, headers=PLC)
        assert r.status_code == 200, (action, r.text)
    before = settled_tcp(cell)
    t = cell.config.target
    recipe = {"name": "plate", "number": 1, "targets": [{
        "points_mm": [list(p) for p in t.points_mm], "dot_diameter_mm": t.dot_diameter_mm}]}
    refused = [
        ("POST", "/api/v1/teach", {"name": "p"}),
        ("DELETE", "/api/v1/teach/p", None),
        ("POST", "/api/v1/calibration/hand-eye", {}),
        ("POST", "/api/v1/calibration/hand-eye/abc/apply", {}),
        ("PUT", "/api/v1/recipes", recipe),
        ("DELETE", "/api/v1/recipes/plate", None),
        ("PUT", "/api/v1/camera/settings", {"exposure_us": 5000}),
        ("POST", "/api/v1/jog", {"mode": "step", "translation_mm": [0, 0, 5]}),
        ("POST", "/api/v1/arm/unlock", None),
        ("POST", "/api/v1/arm/power", {"on": True}),
    ]
    n_jobs = cell.jobs.count_jobs()
    for method, path, body in refused:
        r = client.request(method, path, json=body, headers=PLC)
        assert r.status_code == 403, (method, path, r.status_code, r.text)
        assert r.json()["error"]["code"] == "forbidden"
    assert cell.jobs.count_jobs() == n_jobs
    assert pose_distance(settled_tcp(cell), before)[0] < 0.01
    assert client.get("/api/v1/recipes", headers=PLC).json()["recipes"] == []
    # the operator still may
    r = client.post("/api/v1/arm/home", json={"wait": True}, headers=OP)
    assert r.status_code == 200 and r.json()["state"] == "succeeded", r.text
