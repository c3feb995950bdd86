"""The servo's API surface on the fast simulated cell (in-process arm): roles, refusals that
move nothing, the drifting simulated target and its truth."""

from __future__ import annotations

import time
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest
from fastapi.testclient import TestClient

from api.app import create_app
from cell.service import Cell
from estimator.transforms import T_from_pose_dict, pose_distance
from tests.support.cell import AUTH, running_cell, sim_config, tcp


@pytest.fixture
def client(tmp_path: Path) -> Iterator[TestClient]:
    config = sim_config(tmp_path, servo={"max_track_s": 60.0, "lost_after_s": 1.0})
    with running_cell(config) as cell, TestClient(create_app(cell)) as c:
        yield c


def _cell(client: TestClient) -> Cell:
    cell: Cell = client.app.state.cell  # type: ignore[attr-defined]
    return cell


def test_track_refusals_are_typed_and_move_nothing(client: TestClient) -> None:
    before = tcp(_cell(client))
    r = client.post("/api/v1/track", json={"standoff_mm": 50, "duration_s": 61},
                    headers=AUTH["plc"])
    assert r.status_code == 422 and r.json()["error"]["code"] == "duration_limit", r.text
    r = client.post("/api/v1/track", json={"standoff_mm": 50, "duration_s": 5},
                    headers=AUTH["viewer"])
    assert r.status_code == 403
    r = client.post("/api/v1/track", json={"standoff_mm": 50}, headers=AUTH["plc"])
    assert r.status_code == 422
    r = client.post("/api/v1/approach", json={"mode": "closed_loop"}, headers=AUTH["plc"])
    assert r.status_code == 422
    assert pose_distance(before, tcp(_cell(client)))[0] < 0.01
    assert not [c for c in _cell(client).commanded() if c.kind == "servo"]


def test_the_simulated_target_drifts_from_the_request_on(client: TestClient) -> None:
    truth = client.get("/api/v1/sim/truth", headers=AUTH["viewer"]).json()["T_base_target"]
    r = client.put("/api/v1/sim/target", json={**truth, "velocity_mm_s": [20.0, 0.0, 0.0],
                                               "angular_velocity_deg_s": [0.0, 0.0, 10.0]},
                   headers=AUTH["operator"])
    assert r.status_code == 200, r.text
    t0 = time.monotonic()
    time.sleep(0.5)
    now = T_from_pose_dict(client.get("/api/v1/sim/truth",
                                      headers=AUTH["viewer"]).json()["T_base_target"])
    dt = time.monotonic() - t0
    moved = now[:3, 3] - T_from_pose_dict(truth)[:3, 3]
    assert moved[0] == pytest.approx(20.0 * dt, abs=2.0) and abs(moved[1]) < 1e-6
    assert pose_distance(now, T_from_pose_dict(truth))[1] == pytest.approx(10.0 * dt, abs=1.0)
    r = client.put("/api/v1/sim/target", json={**truth, "velocity_mm_s": [2000.0, 0, 0]},
                   headers=AUTH["operator"])
    assert r.status_code == 422
    assert np.isfinite(now).all()


def test_servo_approach_on_the_in_process_arm(client: TestClient) -> None:
    """The in-process simulated arm streams too (engine speedl with its own watchdog)."""
    from cell.vision.frames import approach_tcp
    from tests.support.cell import world

    cell = _cell(client)
    r = client.post("/api/v1/approach", json={"standoff_mm": 60, "mode": "servo", "wait": True},
                    headers=AUTH["plc"])
    assert r.status_code == 200 and r.json()["state"] == "succeeded", r.text
    time.sleep(0.2)
    goal = approach_tcp(world(cell).true_T_base_target(), np.eye(4), 60)
    d_mm, d_deg = pose_distance(tcp(cell), goal)
    assert d_mm <= 0.3 and d_deg <= 0.1


def test_a_track_the_arm_cannot_keep_up_with_stops_tracking_lag(tmp_path: Path) -> None:
    """A conveyor four times the servo's speed cap: once on its goal the track falls behind by
    more than ``track_lag_mm`` and ends ``tracking_lag`` with the arm still, not chasing the
    target out of view."""
    config = sim_config(tmp_path, servo={"max_track_s": 60.0, "lost_after_s": 1.0,
                                         "max_speed_mm_s": 20.0, "track_lag_mm": 10.0})
    with running_cell(config) as cell, TestClient(create_app(cell)) as client:
        r = client.post("/api/v1/track", json={"standoff_mm": 60, "duration_s": 30},
                        headers=AUTH["plc"])
        assert r.status_code == 200, r.text
        job_id = r.json()["id"]
        deadline = time.monotonic() + 20.0
        while (cell.job(job_id).progress.get("error_mm") or 99.0) > 5.0:  # on its goal
            assert cell.job(job_id).state == "running", cell.job(job_id).error_message
            assert time.monotonic() < deadline, cell.job(job_id).progress
            time.sleep(0.05)
        truth = client.get("/api/v1/sim/truth", headers=AUTH["viewer"]).json()["T_base_target"]
        r = client.put("/api/v1/sim/target", json={**truth, "velocity_mm_s": [80.0, 0.0, 0.0]},
                       headers=AUTH["operator"])
        assert r.status_code == 200, r.text
        deadline = time.monotonic() + 20.0
        while cell.job(job_id).state == "running":
            assert time.monotonic() < deadline, cell.job(job_id).progress
            time.sleep(0.05)
        job = client.get(f"/api/v1/jobs/{job_id}", headers=AUTH["viewer"]).json()
        assert job["state"] == "failed" and job["error"]["code"] == "tracking_lag", job
        assert "cannot keep up" in job["error"]["message"]
        first = tcp(cell)
        time.sleep(0.2)
        assert pose_distance(first, tcp(cell))[0] < 0.05  # still
