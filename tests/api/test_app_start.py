"""``create_app(start_cell=True)``: the path ``cell serve`` takes. The cell is built, not
started, when the app is made (its simulated controller may still be booting); the app's
start-up starts it and serves without waiting for the arm's connect and power-on, the
gripper's activation or the PLC servers' sockets: ``/health`` says ``starting`` until all of
them have ended, then ``ok``. A start that fails closes what it built."""

from __future__ import annotations

import logging
import socket
import threading
import time
from pathlib import Path

import pytest
from fastapi.testclient import TestClient

from api.app import create_app
from api.plc.interfaces import Interfaces
from cell.runtime import build_cell
from cell.supervision.status import still_starting
from tests.support.cell import AUTH, sim_config
from tests.support.net import free_port


def test_the_app_starts_the_cell_beside_its_servers(tmp_path: Path,
                                                    monkeypatch: pytest.MonkeyPatch) -> None:
    port = free_port()  # every server on a free port: sim.toml's fixed ones are fought over
    cell = build_cell(sim_config(
        tmp_path, modbus={"port": port, "host": "127.0.0.1"},
        urscript={"xmlrpc_port": free_port()},
        opcua={"endpoint": f"opc.tcp://127.0.0.1:{free_port()}"}))
    closed: list[bool] = []
    real_close = cell.close
    monkeypatch.setattr(cell, "close", lambda: (closed.append(True), real_close()))
    app = create_app(cell, close_cell_on_shutdown=True, interfaces=True, start_cell=True)
    assert not cell.links.snapshot()["arm"]["up"]  # built, nothing connected yet
    with TestClient(app) as client:
        h = client.get("/api/v1/health").json()
        deadline = time.monotonic() + 60.0
        while still_starting(h):
            assert h["status"] == "degraded", h
            assert time.monotonic() < deadline, "the start did not end in 60 s"
            time.sleep(0.05)
            h = client.get("/api/v1/health").json()
        assert h["status"] == "ok" and h["arm_connected"] and h["camera_connected"], h
        r = client.post("/api/v1/locate", json={}, headers=AUTH["operator"])
        assert r.status_code == 200, r.text
        with socket.create_connection(("127.0.0.1", port), timeout=2.0):
            pass  # the Modbus server listens
    assert closed == [True]


def test_health_says_starting_until_the_plc_servers_listen(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch, caplog: pytest.LogCaptureFixture) -> None:
    port = free_port()
    # as cell serve builds it: the simulated controller boots while the service starts
    cell = build_cell(sim_config(tmp_path, modbus={"port": port, "host": "127.0.0.1"}),
                      wait_ready=False)
    release = threading.Event()
    real_start = Interfaces.start

    def held_start(self: Interfaces) -> None:  # the servers' imports and sockets, held open
        assert release.wait(30.0)
        real_start(self)

    monkeypatch.setattr(Interfaces, "start", held_start)
    caplog.set_level(logging.WARNING)
    app = create_app(cell, close_cell_on_shutdown=True, interfaces=True, start_cell=True)
    with TestClient(app) as client:
        deadline = time.monotonic() + 60.0
        while not (cell.links.snapshot()["arm"]["up"] and cell.links.snapshot()["camera"]["up"]):
            assert time.monotonic() < deadline, "the arm and camera did not connect in 60 s"
            time.sleep(0.05)
        h = client.get("/api/v1/health").json()
        assert h["status"] == "degraded" and still_starting(h), h  # the servers still start
        with pytest.raises(OSError):
            socket.create_connection(("127.0.0.1", port), timeout=1.0).close()
        release.set()
        while still_starting(h := client.get("/api/v1/health").json()):
            assert time.monotonic() < deadline, "the start did not end in 60 s"
            time.sleep(0.05)
        assert h["status"] == "ok", h
        with socket.create_connection(("127.0.0.1", port), timeout=2.0):
            pass  # the Modbus server listens
        assert not {"arm_disconnected", "camera_lost"} & {a.code for a in cell.alarms.list()[0]}
    # the controller's boot was waited for, not mistaken for an unreachable arm
    assert not [r for r in caplog.records if "connect try" in r.getMessage()], caplog.text


def test_a_start_that_fails_closes_the_cell(tmp_path: Path,
                                            monkeypatch: pytest.MonkeyPatch) -> None:
    cell = build_cell(sim_config(tmp_path))
    closed: list[bool] = []
    real_close = cell.close
    monkeypatch.setattr(cell, "start",
                        lambda *_: (_ for _ in ()).throw(RuntimeError("boom")))
    monkeypatch.setattr(cell, "close", lambda: (closed.append(True), real_close()))
    app = create_app(cell, close_cell_on_shutdown=True, start_cell=True)
    with pytest.raises(RuntimeError, match="boom"), TestClient(app):
        pass
    assert closed == [True]


def test_commands_while_the_arm_powers_on_at_start_are_refused_and_move_nothing(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    cell = build_cell(sim_config(tmp_path))
    raw = cell.core.arm.raw
    powered, release = threading.Event(), threading.Event()
    real_power_on = raw.power_on

    def held_power_on() -> None:  # the power-on a real arm takes seconds for, held open
        powered.set()
        assert release.wait(30.0)
        real_power_on()

    monkeypatch.setattr(raw, "power_on", held_power_on)
    app = create_app(cell, close_cell_on_shutdown=True, start_cell=True)
    with TestClient(app) as client:
        assert powered.wait(30.0)
        h = client.get("/api/v1/health").json()
        assert h["status"] == "degraded" and still_starting(h), h
        before = list(cell.commanded())
        for path, body in (("/api/v1/arm/home", {"wait": True}),
                           ("/api/v1/jog", {"mode": "continuous", "linear_mm_s": [5.0, 0.0, 0.0]})):
            r = client.post(path, json=body, headers=AUTH["operator"])
            assert r.status_code in (409, 503), r.text
            assert r.json()["error"]["code"] in ("busy", "arm_disconnected"), r.text
        assert list(cell.commanded()) == before
        assert client.post("/api/v1/stop", json={}, headers=AUTH["operator"]).json()["stopped"]
        release.set()
        deadline = time.monotonic() + 60.0
        while still_starting(h := client.get("/api/v1/health").json()):
            assert time.monotonic() < deadline, "the start did not end in 60 s"
            time.sleep(0.05)
        assert h["status"] == "ok", h
        r = client.post("/api/v1/arm/home", json={"wait": True}, headers=AUTH["operator"])
        assert r.status_code == 200 and r.json()["state"] == "succeeded", r.text
        time.sleep(1.5)  # the alarm watch has looked at least twice since the start ended
        raised = [a.code for a in cell.alarms.list()[0]]
        assert not {"arm_disconnected", "camera_lost"} & set(raised), raised
