"""The hand-eye routine through the HTTP API on the simulated cell: end to end against the
simulator's true camera mount, progress over server-sent events, stop, and apply (running cell
and config file) only on request."""

from __future__ import annotations

import json
import shutil
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from fastapi.testclient import TestClient

from api.app import create_app
from cell.calibration.dataset import load_dataset
from cell.calibration.solve import solve_dataset
from cell.config.schema import load_config
from cell.service import Cell
from estimator.transforms import T_from_pose_dict, pose_distance
from tests.support.cell import AUTH, running_cell, sim_config, tcp, world
from tests.support.jobs import wait_job
from tests.support.paths import REPO

OP, PLC, VIEW = AUTH["operator"], AUTH["plc"], AUTH["viewer"]
# The simulator's true camera mount; the config's [hand_eye] guess is millimetres off.
TRUE_T_FLANGE_CAMERA: dict[str, Any] = {"position_mm": [3.0, 57.5, 34.0],
                                        "rotvec_rad": [0.012, -0.02, 0.03]}
BASE = "/api/v1/calibration/hand-eye"


@pytest.fixture
def client(tmp_path: Path) -> Iterator[TestClient]:
    config_file = tmp_path / "cell.toml"  # the file apply may write
    shutil.copy(REPO / "cell" / "configs" / "sim.toml", config_file)
    config = sim_config(tmp_path, sim={"T_flange_camera": TRUE_T_FLANGE_CAMERA})
    with running_cell(config, config_file) as cell, TestClient(create_app(cell)) as c:
        yield c


def cell_of(client: TestClient) -> Cell:
    cell: Cell = client.app.state.cell  # type: ignore[attr-defined]
    return cell


def sse_events(client: TestClient, n: int) -> list[dict[str, Any]]:
    with client.stream("GET", f"/api/v1/calibration/events?max_events={n}", headers=VIEW) as r:
        assert r.status_code == 200
        text = "".join(r.iter_text())
    return [json.loads(line[len("data: "):]) for line in text.splitlines()
            if line.startswith("data: ")]


def locate_error_mm(client: TestClient) -> float:
    r = client.post("/api/v1/locate", json={"n_frames": 3}, headers=PLC)
    assert r.status_code == 200, r.text
    T = T_from_pose_dict(r.json()["T_base_target"])
    return pose_distance(T, world(cell_of(client)).true_T_base_target())[0]


def test_hand_eye_routine_end_to_end(client: TestClient, tmp_path: Path) -> None:
    cell = cell_of(client)
    truth = T_from_pose_dict(TRUE_T_FLANGE_CAMERA)
    guess = cell.frames.T_flange_camera.copy()
    error_before = locate_error_mm(client)
    start = tcp(cell)

    # 8 views (two spare above the 6 the routine needs): this test checks the HTTP flow
    # (progress, busy, apply, backup, refusal) and the result against the truth within a looser
    # bound (6 views measured 0.02-0.06 mm / 0.015 deg); the 0.2 mm / 0.05 deg requirement is
    # checked with 12 views by test_calibrate_cli.py's test_routine_recovers_the_simulated_hand_eye.
    r = client.post(BASE, json={"views": 8, "speed_mm_s": 250, "tilt_deg": 18, "roll_deg": 35},
                    headers=OP)
    assert r.status_code == 200, r.text
    job_id = r.json()["id"]
    assert r.json()["state"] == "running" and r.json()["kind"] == "hand_eye_calibration"
    # one motion at a time
    r = client.post(BASE, json={"views": 8}, headers=OP)
    assert r.status_code == 409 and r.json()["error"]["code"] == "busy"
    r = client.post("/api/v1/approach", json={}, headers=PLC)
    assert r.status_code == 409 and r.json()["error"]["code"] == "busy"
    r = client.post("/api/v1/teach", json={"name": "during"}, headers=OP)
    assert r.status_code == 409 and r.json()["error"]["code"] == "busy"
    assert client.get("/api/v1/status", headers=VIEW).json()["state"] == "calibration"

    events = sse_events(client, 3)
    assert all(e["type"] == "calibration" and e["job_id"] == job_id for e in events)
    assert all({"stage", "done", "total"} <= set(e) for e in events), events
    assert any(e["done"] >= 1 for e in events)

    t0 = time.monotonic()
    job = wait_job(client, job_id, 120.0, url=BASE)
    assert job["state"] == "succeeded", job["error"]
    print(f"calibration job finished {time.monotonic() - t0:.1f} s after the events")
    result = job["result"]
    assert set(result["methods"]) >= {"tsai", "park"}
    for m in result["methods"].values():
        assert set(m["T_flange_camera"]) == {"position_mm", "rotvec_rad"}
        assert m["residual"]["mean_mm"] < 1.0
    assert result["verdict"]["consistent"] is True and result["verdict"]["text"]
    # auto: the joint fit, the simulated arm here reporting exact poses; the hybrid beside it
    assert result["chosen"] == "joint" and result["joint"]["rms_px"] < 0.5
    assert result["hybrid"]["rms_px"] < 0.5
    d_mm, d_deg = pose_distance(T_from_pose_dict(result["T_flange_camera"]), truth)
    print(f"hand-eye via API: {d_mm:.3f} mm / {d_deg:.4f} deg from the truth "
          f"(guess was {pose_distance(guess, truth)[0]:.2f} mm off)")
    assert d_mm < 0.3 and d_deg < 0.1
    assert pose_distance(tcp(cell), start)[0] < 0.2  # back at its start pose
    # the views are kept as a dataset that re-solves offline to the same answer
    saved = result["dataset"]
    assert saved["saved"] is True and saved["views"] == len(result["views"])
    assert Path(saved["folder"]) == tmp_path / "calibration" / f"hand-eye-{job_id}"
    again = solve_dataset(load_dataset(saved["folder"]))
    d_mm, d_deg = pose_distance(again.T_flange_camera, T_from_pose_dict(result["T_flange_camera"]))
    assert d_mm < 1e-3 and d_deg < 1e-4
    # nothing applied without a request
    assert np.allclose(cell.frames.T_flange_camera, guess)
    assert load_config(tmp_path / "cell.toml").hand_eye.T_flange_camera.T()[1, 3] == 60.0

    assert client.post(f"{BASE}/{job_id}/apply", json={}, headers=PLC).status_code == 403
    r = client.post(f"{BASE}/{job_id}/apply", json={"write_config": True}, headers=OP)
    assert r.status_code == 200, r.text
    applied = T_from_pose_dict(r.json()["T_flange_camera"])
    assert pose_distance(applied, truth)[0] < 0.3
    assert np.allclose(cell.frames.T_flange_camera, applied)
    assert np.allclose(cell.config.hand_eye.T_flange_camera.T(), applied)
    written = load_config(tmp_path / "cell.toml")
    assert pose_distance(written.hand_eye.T_flange_camera.T(), applied)[0] < 1e-6
    assert written.tool == load_config().tool  # only [hand_eye] changed
    change = r.json()["config_change"]  # the old file is kept as a timestamped backup
    sim_toml = (REPO / "cell" / "configs" / "sim.toml").read_text()
    assert Path(change["backup"]).read_text() == sim_toml
    assert change["old_T_flange_camera"]["position_mm"] == [0.0, 60.0, 30.0]
    # a file that is no valid cell config is refused, and left as it was
    good = (tmp_path / "cell.toml").read_text()
    broken = good.replace('kind = "ur"', 'kinds = "ur"', 1)  # in [robot]
    assert broken != good
    (tmp_path / "cell.toml").write_text(broken)
    r = client.post(f"{BASE}/{job_id}/apply", json={"write_config": True}, headers=OP)
    assert r.status_code == 409 and r.json()["error"]["code"] == "config_write_failed", r.text
    assert "not a valid cell config" in r.json()["error"]["message"]
    assert (tmp_path / "cell.toml").read_text() == broken
    error_after = locate_error_mm(client)
    print(f"locate error with the guess {error_before:.2f} mm, after apply {error_after:.3f} mm")
    assert error_before > 2.0 and error_after < 0.5


def test_refusals_and_stop(client: TestClient) -> None:
    cell = cell_of(client)
    assert client.post(BASE, json={}, headers=VIEW).status_code == 403
    assert client.post(BASE, json={}, headers=PLC).status_code == 403
    for body in ({"views": 2}, {"tilt_deg": 60}, {"method": "magic"}, {"view": 8}):
        r = client.post(BASE, json=body, headers=OP)
        assert r.status_code == 422 and r.json()["error"]["code"] == "invalid_request", body
    r = client.get(f"{BASE}/nope", headers=VIEW)
    assert r.status_code == 404 and r.json()["error"]["code"] == "job_not_found"
    assert client.post(f"{BASE}/nope/apply", json={}, headers=OP).status_code == 404
    r = client.post(BASE, json={"views": 8, "speed_mm_s": 1000}, headers=OP)
    assert r.status_code == 422 and r.json()["error"]["code"] == "speed_limit"

    r = client.post(BASE, json={"views": 8}, headers=OP)
    assert r.status_code == 200, r.text
    job_id = r.json()["id"]
    events = sse_events(client, 2)  # the routine is under way
    assert events[-1]["job_id"] == job_id
    assert client.post("/api/v1/stop", json={"reason": "test"}, headers=VIEW).status_code == 200
    job = wait_job(client, job_id, 20.0, url=BASE)
    assert job["state"] == "cancelled", job
    time.sleep(0.2)
    resting = tcp(cell)
    time.sleep(0.5)  # nothing moves after a stop, not even the return to the start pose
    assert pose_distance(tcp(cell), resting)[0] < 0.01
    r = client.post(f"{BASE}/{job_id}/apply", json={}, headers=OP)
    assert r.status_code == 409 and r.json()["error"]["code"] == "job_not_succeeded"
    # the cell is free again
    r = client.post("/api/v1/jog", json={"mode": "step", "translation_mm": [0, 0, 5]},
                    headers=OP)
    assert r.status_code == 200, r.text
