"""The `make run` wiring over HTTP: the simulated UR controller in its own process on its own
loopback address, driven through the real UR adapter and ur_rtde; the simulated camera follows
that controller's arm; the fake gripper on a pty is driven through the Modbus RTU adapter."""

from __future__ import annotations

import time
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest
from fastapi.testclient import TestClient

from api.app import create_app
from cell.service import Cell
from cell.vision.frames import approach_tcp
from estimator.transforms import T_from_pose_dict, pose_distance, translation_T
from fakes.ur_controller.process import free_loopback_host
from tests.support.cell import AUTH, running_cell, settled_tcp, sim_config, world


@pytest.fixture
def client(tmp_path: Path) -> Iterator[TestClient]:
    # the longest dead-man allowed: the jog test is of jogging through ur_rtde, and on a
    # loaded host one heartbeat request through this process can take most of the default
    config = sim_config(tmp_path, robot="ur", host=free_loopback_host(), gripper="sim",
                        approach={"speed_mm_s": 250.0, "accel_mm_s2": 1500.0},
                        limits={"deadman_timeout_s": 0.25})
    with running_cell(config) as cell, TestClient(create_app(cell)) as c:
        yield c


def test_locate_approach_and_grip_through_ur_rtde(client: TestClient) -> None:
    cell: Cell = client.app.state.cell  # type: ignore[attr-defined]
    status = client.get("/api/v1/status", headers=AUTH["viewer"]).json()
    assert status["robot"]["mode"] == "RUNNING" and status["gripper"]["activated"]
    # the plate on a 30 mm fixture, so that its grasp pose (its origin) is inside the workspace
    world(cell).set_target(translation_T(0.0, 0.0, 30.0) @ world(cell).true_T_base_target())
    r = client.post("/api/v1/locate", json={"n_frames": 2}, headers=AUTH["plc"])
    assert r.status_code == 200, r.text
    T_true = world(cell).true_T_base_target()
    d_mm, d_deg = pose_distance(T_from_pose_dict(r.json()["T_base_target"]), T_true)
    assert d_mm <= 0.5 and d_deg <= 0.1
    r = client.post("/api/v1/approach", json={"standoff_mm": 30, "wait": True},
                    headers=AUTH["plc"])
    assert r.status_code == 200 and r.json()["state"] == "succeeded", r.text
    d_mm, d_deg = pose_distance(world(cell).true_T_base_tcp(), approach_tcp(T_true, np.eye(4), 30))
    print(f"final TCP error through ur_rtde: {d_mm:.3f} mm / {d_deg:.3f} deg")
    assert d_mm <= 0.3 and d_deg <= 0.1
    # down the last 30 mm along the tool axis to the plate's grasp pose, and take it
    r = client.post("/api/v1/jog", json={"mode": "step", "frame": "tool",
                                         "translation_mm": [0, 0, 30]}, headers=AUTH["operator"])
    assert r.status_code == 200, r.text
    settled_tcp(cell)
    r = client.post("/api/v1/gripper", json={"action": "close"}, headers=AUTH["operator"])
    assert r.status_code == 200 and r.json()["object_detected"], r.text
    assert any(p.held for p in world(cell).parts_truth())
    r = client.post("/api/v1/gripper", json={"action": "move", "position_mm": 60},
                    headers=AUTH["operator"])
    assert r.status_code == 200 and abs(r.json()["position_mm"] - 60) < 1.0, r.text
    # continuous jog through ur_rtde, ended by the dead-man
    z0 = world(cell).true_T_base_tcp()[2, 3]
    r = client.post("/api/v1/jog", json={"mode": "continuous", "linear_mm_s": [0, 0, 30]},
                    headers=AUTH["operator"])
    assert r.status_code == 200, r.text
    t_end = time.monotonic() + 0.8
    last = time.monotonic()
    while time.monotonic() < t_end:  # heartbeats back to back: the gap is one request's time
        sent = time.monotonic()
        hb = client.post("/api/v1/jog/heartbeat", headers=AUTH["operator"])
        took = time.monotonic() - sent
        assert hb.status_code == 200, (
            f"{hb.text}; heartbeat sent {sent - last:.3f} s after the last (or the jog's start "
            f"answer), took {took:.3f} s; "
            f"{_jog_end(cell)}")
        last = sent
        time.sleep(0.01)
    deadline = time.monotonic() + 3
    while client.get("/api/v1/status", headers=AUTH["viewer"]).json()["state"] == "jog":
        assert time.monotonic() < deadline
        time.sleep(0.02)
    time.sleep(0.5)
    rise = world(cell).true_T_base_tcp()[2, 3] - z0
    assert 15 < rise < 45, f"rose {rise:.1f} mm; {_jog_end(cell)}"  # ~1 s at 30 mm/s


def _jog_end(cell: Cell) -> str:
    """Why the last continuous jog ended, as the audit has it (the jog's thread notes its end
    just after it lets the motion slot go)."""
    deadline = time.monotonic() + 2.0
    while not (ends := [e for e in cell.jobs.audit_log(50) if e.command == "jog_end"]):
        if time.monotonic() > deadline:
            return "no jog_end in the audit"
        time.sleep(0.02)
    return f"jog ended: {ends[0].detail}; the controller said: {_controller_said(cell)}"


def _controller_said(cell: Cell) -> list[str]:
    """The simulated controller's last messages (why its control script stopped)."""
    ctl = getattr(getattr(cell.sim, "_truth", None), "ctl", None)
    try:
        return list(ctl.state()["messages"][-5:]) if ctl is not None else []
    except Exception as exc:  # a diagnostic only
        return [f"(no state: {exc})"]


def test_protective_stop_mid_approach_through_ur_rtde(client: TestClient) -> None:
    cell: Cell = client.app.state.cell  # type: ignore[attr-defined]
    r = client.post("/api/v1/approach", json={"standoff_mm": 30}, headers=AUTH["plc"])
    assert r.status_code == 200, r.text
    job_id = r.json()["id"]
    time.sleep(0.8)
    world(cell).trigger_protective_stop("test")
    deadline = time.monotonic() + 20
    while (job := client.get(f"/api/v1/jobs/{job_id}", headers=AUTH["viewer"]).json())[
            "state"] == "running":
        assert time.monotonic() < deadline
        time.sleep(0.05)
    assert job["state"] == "failed" and job["error"]["code"] == "protective_stop", job
    held = settled_tcp(cell)
    r = client.post("/api/v1/jog", json={"mode": "step", "translation_mm": [0, 0, 5]},
                    headers=AUTH["operator"])
    assert r.status_code == 409 and r.json()["error"]["code"] == "protective_stop", r.text
    time.sleep(0.3)
    assert pose_distance(world(cell).true_T_base_tcp(), held)[0] < 0.01
