"""``create_app(start_cell=True)``: the path ``cell serve`` takes. The cell is built, not
started, when the app is made; the app's start-up starts it beside the PLC servers, and the
first request already finds it connected. A start that fails closes what it built."""

from __future__ import annotations

import socket
from pathlib import Path

import pytest
from fastapi.testclient import TestClient

from api.app import create_app
from cell.runtime import build_cell
from tests.support.cell import AUTH, sim_config
from tests.support.net import free_port


def test_the_app_starts_the_cell_beside_its_servers(tmp_path: Path,
                                                    monkeypatch: pytest.MonkeyPatch) -> None:
    port = free_port()
    cell = build_cell(sim_config(tmp_path, modbus={"port": port, "host": "127.0.0.1"}))
    closed: list[bool] = []
    real_close = cell.close
    monkeypatch.setattr(cell, "close", lambda: (closed.append(True), real_close()))
    app = create_app(cell, close_cell_on_shutdown=True, interfaces=True, start_cell=True)
    assert not cell.links.snapshot()["arm"]["up"]  # built, nothing connected yet
    with TestClient(app) as client:
        h = client.get("/api/v1/health").json()
        assert h["status"] == "ok" and h["arm_connected"] and h["camera_connected"], h
        r = client.post("/api/v1/locate", json={}, headers=AUTH["operator"])
        assert r.status_code == 200, r.text
        with socket.create_connection(("127.0.0.1", port), timeout=2.0):
            pass  # the Modbus server listens
    assert closed == [True]


def test_a_start_that_fails_closes_the_cell(tmp_path: Path,
                                            monkeypatch: pytest.MonkeyPatch) -> None:
    cell = build_cell(sim_config(tmp_path))
    closed: list[bool] = []
    real_close = cell.close
    monkeypatch.setattr(cell, "start", lambda: (_ for _ in ()).throw(RuntimeError("boom")))
    monkeypatch.setattr(cell, "close", lambda: (closed.append(True), real_close()))
    app = create_app(cell, close_cell_on_shutdown=True, start_cell=True)
    with pytest.raises(RuntimeError, match="boom"), TestClient(app):
        pass
    assert closed == [True]
