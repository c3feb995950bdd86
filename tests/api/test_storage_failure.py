"""A job database that stops taking writes mid-job (a full disk), on the simulated cell with
every interface served: the job ends for every door within 1 s with the arm still (HTTP's
``wait: true`` caller, OPC UA's JobState, Modbus' state register, the event stream), the
``storage_failed`` alarm is raised, new jobs are refused with that code while STOP and status
are served, and everything kept in memory is written once the disk takes writes again.

The failing disk is the job database opened read-only under the running stores: every write
fails in SQLite as on a file system that refuses them, every read still works."""

from __future__ import annotations

import asyncio
import sqlite3
import threading
import time
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from fastapi.testclient import TestClient
from pymodbus.client import ModbusTcpClient

from api.app import create_app
from api.plc.modbus import Command, Ir, ModbusServer, State, float_words
from api.plc.opcua import OpcUaServer
from cell.config.endpoints import opcua_cert_dir
from cell.jobs.events import Subscription
from cell.service import Cell
from tests.support.cell import AUTH, running_cell, sim_config, tcp
from tests.support.net import free_port
from tests.support.opcua import Opc, opc_client
from tests.support.waiting import wait_until

OP, VIEW = AUTH["operator"], AUTH["viewer"]
DOOR_S = 1.0  # the job ends for every door within this of the disk failing


@dataclass
class Served:
    cell: Cell
    http: TestClient
    opcua_url: str
    modbus_port: int
    db: Path


@pytest.fixture
def served(tmp_path: Path) -> Iterator[Served]:
    opcua_port, modbus_port = free_port(), free_port()
    config = sim_config(tmp_path, approach={"speed_mm_s": 25.0, "accel_mm_s2": 500.0},
                        opcua={"endpoint": f"opc.tcp://127.0.0.1:{opcua_port}"},
                        modbus={"port": modbus_port, "clients": ["127.0.0.1"]})
    with running_cell(config) as cell, TestClient(create_app(cell)) as http:
        opcua = OpcUaServer(cell, config.opcua, opcua_cert_dir(config))
        modbus = ModbusServer(cell, config.modbus)
        opcua.start()
        modbus.start()
        try:
            yield Served(cell, http, f"opc.tcp://127.0.0.1:{opcua_port}", modbus_port,
                         tmp_path / "jobs.db")
        finally:
            modbus.close()
            opcua.close()


@contextmanager
def failing_disk(s: Served) -> Iterator[float]:
    """Every write to the job database fails from now (yields when, time.monotonic()) until
    the block ends."""
    stores: list[Any] = [s.cell.jobs, s.cell.alarms]
    saved = []
    for store in stores:
        ro = sqlite3.connect(f"file:{s.db}?mode=ro", uri=True, check_same_thread=False,
                             isolation_level=None)
        with store._lock:
            saved.append(store._db)
            store._db = ro
    try:
        yield time.monotonic()
    finally:
        for store, db in zip(stores, saved, strict=True):
            with store._lock:
                store._db.close()
                store._db = db


def job_ended_event(sub: Subscription, job_id: str, timeout_s: float) -> float:
    """When (time.monotonic()) the event stream said the job ended."""
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        event = sub.get(timeout_s=0.05)
        if event and event["type"] == "job" and event["job"]["id"] == job_id \
                and event["job"]["state"] != "running":
            return time.monotonic()
    raise AssertionError("no job end on the event stream")


def moving(cell: Cell) -> dict[str, Any]:
    """The running job once the arm has moved 3 mm from where it was."""
    start = tcp(cell)[:3, 3]
    wait_until(lambda: np.linalg.norm(tcp(cell)[:3, 3] - start) > 3.0, 30, "the arm moving")
    job = cell.status()["job"]
    assert job is not None and job["state"] == "running", job
    return dict(job)


def arm_still(cell: Cell) -> bool:
    a = tcp(cell)
    time.sleep(0.1)
    return bool(np.allclose(a, tcp(cell), atol=1e-6))


def stored_row(db: Path, job_id: str) -> tuple[Any, ...]:
    con = sqlite3.connect(db)
    row = con.execute("SELECT state, error_code, ended_at FROM jobs WHERE id = ?",
                      (job_id,)).fetchone()
    con.close()
    return tuple(row)


def test_a_disk_that_fails_mid_job_ends_it_for_http_opcua_and_the_event_stream(
        served: Served) -> None:
    s, cell = served, served.cell
    answer: dict[str, Any] = {}

    def wait_caller() -> None:
        r = s.http.post("/api/v1/approach", json={"standoff_mm": 60, "wait": True}, headers=OP)
        answer.update(status=r.status_code, body=r.json(), at=time.monotonic())

    async def opc_end(job_id: str, t0: float) -> float:
        async with Opc(opc_client(s.opcua_url, "plc")) as opc:
            await opc.wait_for("JobId", lambda v: v == job_id, 10)
            await opc.wait_for("JobState", lambda v: v == "failed", t0 + DOOR_S + 5
                               - time.monotonic())
            return time.monotonic()

    with cell.events.subscribe() as sub:
        caller = threading.Thread(target=wait_caller)
        caller.start()
        job = moving(cell)
        with failing_disk(s) as t0:
            at_opc = asyncio.run(opc_end(job["id"], t0))
            at_event = job_ended_event(sub, job["id"], 5)
            caller.join(10)
            assert answer["status"] == 200, answer
            ended = answer["body"]
            assert ended["id"] == job["id"] and ended["state"] == "failed", ended
            assert ended["error"]["code"] == "storage_failed", ended
            for door, at in (("http", answer["at"]), ("opcua", at_opc), ("events", at_event)):
                assert at - t0 <= DOOR_S + 0.5, (door, at - t0)  # + the doors' own polling
            assert at_event - t0 <= DOOR_S, at_event - t0
            assert arm_still(cell)

            health = s.http.get("/api/v1/health").json()
            assert health["status"] == "degraded"
            assert "storage" in [r["code"] for r in health["reasons"]], health
            def active_alarms() -> list[tuple[str, str | None]]:
                r = s.http.get("/api/v1/alarms", params={"active": "true"}, headers=VIEW)
                return [(a["code"], a["job_id"]) for a in r.json()["alarms"]]

            wait_until(lambda: set(active_alarms()) == {("storage_failed", None),
                                                         ("storage_failed", job["id"])},
                       2, "the storage alarm and the job's")
            r = s.http.post("/api/v1/arm/home", json={}, headers=OP)
            assert r.status_code == 503 and r.json()["error"]["code"] == "storage_failed", r.text
            assert s.http.post("/api/v1/stop", json={}, headers=OP).json()["stopped"]
            assert s.http.get("/api/v1/status", headers=VIEW).status_code == 200
            assert s.http.get(f"/api/v1/jobs/{job['id']}",
                              headers=VIEW).json()["state"] == "failed"
            assert stored_row(s.db, job["id"])[0] == "running"  # not written: kept in memory

    # the disk takes writes again: everything kept is written, jobs start again
    wait_until(lambda: s.http.get("/api/v1/health").json()["status"] == "ok", 10, "health ok")
    state, code, ended_at = stored_row(s.db, job["id"])
    assert (state, code) == ("failed", "storage_failed") and ended_at == ended["ended_at"]
    def stored_alarms() -> list[tuple[str, str | None]]:
        con = sqlite3.connect(s.db)
        rows = con.execute("SELECT code, job_id FROM alarms").fetchall()
        con.close()
        return rows

    rows = wait_until(lambda: len(r := stored_alarms()) >= 2 and r, 5, "the alarms written")
    assert sorted(rows, key=str) == sorted([("storage_failed", None),
                                            ("storage_failed", job["id"])], key=str), rows
    r = s.http.post("/api/v1/arm/home", json={"wait": True}, headers=OP)
    assert r.status_code == 200 and r.json()["state"] == "succeeded", r.text


def test_a_disk_that_fails_mid_job_ends_it_for_modbus(served: Served) -> None:
    s, cell = served, served.cell
    client = ModbusTcpClient("127.0.0.1", port=s.modbus_port, timeout=5)
    assert client.connect()
    try:
        r = client.write_registers(0, [Command.APPROACH, 1, 0, *float_words(60.0)],
                                   device_id=1)
        assert not r.isError(), r

        def inputs() -> list[int]:
            regs = client.read_input_registers(0, count=23, device_id=1)
            assert not regs.isError(), regs
            return list(regs.registers)

        assert moving(cell)["kind"] == "approach"
        assert inputs()[Ir.STATE] == State.BUSY
        with failing_disk(s) as t0:
            regs = wait_until(lambda: (r := inputs())[Ir.FINISHED_SEQUENCE] == 1 and r,
                              DOOR_S + 1, "modbus: the job ended")
            assert time.monotonic() - t0 <= DOOR_S + 0.2  # + the 10 ms polling
            assert regs[Ir.STATE] == State.FAILED
            assert arm_still(cell)
    finally:
        client.close()


def test_a_start_on_a_disk_that_takes_no_writes_serves_degraded(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    config = sim_config(tmp_path)
    db = tmp_path / "jobs.db"
    with running_cell(config) as cell:
        job = cell.jobs.create("home", "plc", {})  # left running: the service is killed
        cell.jobs._db.execute("UPDATE jobs SET pid = 1 WHERE id = ?", (job.id,))
    con = sqlite3.connect(db)
    con.execute("UPDATE jobs SET state = 'running', ended_at = NULL WHERE id = ?", (job.id,))
    con.commit()
    con.close()
    real = sqlite3.connect

    def read_only(database: Any, *args: Any, **kwargs: Any) -> sqlite3.Connection:
        if str(database) == str(db):
            return real(f"file:{db}?mode=ro", *args, uri=True, **kwargs)
        return real(database, *args, **kwargs)

    monkeypatch.setattr(sqlite3, "connect", read_only)
    with running_cell(config) as cell, TestClient(create_app(cell)) as http:
        h = wait_until(lambda: (h := http.get("/api/v1/health").json())["status"] == "degraded"
                       and h, 10, "degraded")
        assert "storage" in [r["code"] for r in h["reasons"]], h
        assert http.get(f"/api/v1/jobs/{job.id}", headers=VIEW).json()["state"] == \
            "interrupted"
        r = http.post("/api/v1/arm/home", json={}, headers=OP)
        assert r.status_code == 503 and r.json()["error"]["code"] == "storage_failed", r.text
        assert http.post("/api/v1/stop", json={}, headers=OP).status_code == 200
        assert http.get("/api/v1/status", headers=VIEW).status_code == 200
