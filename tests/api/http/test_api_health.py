"""``/health`` tells the truth on the simulated cell: a safety-stopped arm, a job database that
cannot be written and a nearly full disk make it ``degraded`` with the reasons, always 200;
and a locate with the arm's link down is ``arm_disconnected``, not a stale pose history."""

from __future__ import annotations

import shutil
import sqlite3
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
from fastapi.testclient import TestClient

from api.app import create_app
from cell.service import Cell
from cell.supervision import storage
from cell.supervision.status import health_from
from tests.support.cell import AUTH, running_cell, sim_config, world
from tests.support.waiting import wait_until

OP, PLC = AUTH["operator"], AUTH["plc"]


@pytest.fixture
def client(tmp_path: Path) -> Iterator[TestClient]:
    # a lost arm link stays lost for the test (the supervisor retries after a minute)
    config = sim_config(tmp_path)
    config = config.model_copy(update={"robot": config.robot.model_copy(
        update={"reconnect_initial_s": 60.0, "reconnect_max_s": 60.0})})
    with running_cell(config) as cell, TestClient(create_app(cell)) as c:
        yield c


def cell_of(client: TestClient) -> Cell:
    cell: Cell = client.app.state.cell  # type: ignore[attr-defined]
    return cell


def health(client: TestClient) -> dict[str, Any]:
    r = client.get("/api/v1/health")
    assert r.status_code == 200, r.text  # liveness: 200 whatever the cell's state
    body: dict[str, Any] = r.json()
    return body


def codes(client: TestClient) -> list[str]:
    return [reason["code"] for reason in health(client)["reasons"]]


def test_protective_stop_is_degraded_until_unlocked(client: TestClient) -> None:
    ok = wait_until(lambda: (h := health(client))["status"] == "ok" and h, 10, "health ok")
    assert ok["reasons"] == [] and ok["missing"] == [] and ok["arm_connected"]
    world(cell_of(client)).trigger_protective_stop("test: collision")
    h = wait_until(lambda: (h := health(client))["status"] == "degraded" and h, 5,
                   "health degraded")
    assert [r["code"] for r in h["reasons"]] == ["protective_stop"], h
    assert "unlock" in h["reasons"][0]["message"]
    assert h["missing"] == [] and h["arm_connected"] and h["camera_connected"]
    assert codes(client) == ["protective_stop"]  # it stays so
    # the controller takes an unlock 5 s after the stop at the earliest; degraded until then
    r = wait_until(lambda: (r := client.post("/api/v1/arm/unlock", headers=OP)).status_code
                   != 409 and r, 15, "the unlock", poll_s=0.5)
    assert r.status_code == 200 and r.json()["unlocked"], r.text
    wait_until(lambda: health(client)["status"] == "ok", 10, "health ok after the unlock")
    assert codes(client) == []


def test_emergency_stop_and_missing_devices_are_reasons() -> None:
    robot = {"connected": True, "safety": "ROBOT_EMERGENCY_STOP", "protective_stop": False}
    h = health_from([], robot)
    assert h["status"] == "degraded" and [r["code"] for r in h["reasons"]] == ["emergency_stop"]
    h = health_from(["arm", "camera"], {"connected": False})
    assert [r["code"] for r in h["reasons"]] == ["arm_disconnected", "camera_lost"]
    assert not h["arm_connected"] and not h["camera_connected"]
    assert health_from([], {"connected": True, "safety": "NORMAL"})["status"] == "ok"


def test_a_job_database_that_cannot_be_written_is_degraded(client: TestClient,
                                                           tmp_path: Path) -> None:
    store = cell_of(client).jobs
    wait_until(lambda: health(client)["status"] == "ok", 10, "health ok")
    writable = store._db
    # the same database, opened read-only: every write fails as on a read-only file system
    store._db = sqlite3.connect(f"file:{tmp_path / 'jobs.db'}?mode=ro", uri=True,
                                check_same_thread=False, isolation_level=None)
    try:
        h = wait_until(lambda: (h := health(client))["status"] == "degraded" and h,
                       4 * storage.CHECK_PERIOD_S + 5, "health degraded by the store")
        assert [r["code"] for r in h["reasons"]] == ["storage"], h
        assert "readonly" in h["reasons"][0]["message"]
        assert h["missing"] == []
        # reads still work
        assert client.get("/api/v1/jobs", headers=PLC).status_code == 200
    finally:
        store._db.close()
        store._db = writable
    wait_until(lambda: health(client)["status"] == "ok", 4 * storage.CHECK_PERIOD_S + 5,
               "health ok once the database is writable again")


def test_a_disk_near_full_is_degraded(client: TestClient,
                                      monkeypatch: pytest.MonkeyPatch) -> None:
    wait_until(lambda: health(client)["status"] == "ok", 10, "health ok")
    real = shutil.disk_usage
    full = real("/")._replace(total=100 * 2**30, used=100 * 2**30 - 200 * 2**20,
                              free=200 * 2**20)
    monkeypatch.setattr(shutil, "disk_usage", lambda path: full)
    h = wait_until(lambda: (h := health(client))["status"] == "degraded" and h,
                   4 * storage.CHECK_PERIOD_S + 5, "health degraded by the disk")
    assert [r["code"] for r in h["reasons"]] == ["disk_space"], h
    assert "200 MB free" in h["reasons"][0]["message"]
    # 5 % of the disk is the other bound: 1 GB free of 40 GB is also near full
    monkeypatch.setattr(shutil, "disk_usage",
                        lambda path: full._replace(total=40 * 2**30, free=2**30))
    storage_watch = cell_of(client).storage
    storage_watch.check()
    assert [r["code"] for r in storage_watch.reasons()] == ["disk_space"]
    monkeypatch.setattr(shutil, "disk_usage", real)
    wait_until(lambda: health(client)["status"] == "ok", 4 * storage.CHECK_PERIOD_S + 5,
               "health ok with room on the disk")


def test_locate_without_the_arm_is_arm_disconnected(client: TestClient) -> None:
    cell = cell_of(client)
    r = client.post("/api/v1/locate", headers=PLC)
    assert r.status_code == 200, r.text
    cell.arm.raw.disconnect()
    r = client.post("/api/v1/locate", headers=PLC)
    assert r.status_code == 503 and r.json()["error"]["code"] == "arm_disconnected", r.text
    h = wait_until(lambda: (h := health(client))["missing"] == ["arm"] and h, 5, "arm missing")
    assert h["status"] == "degraded" and codes(client) == ["arm_disconnected"]
