"""End to end over HTTP on the simulated cell (in-process arm): locate and approach accuracy
against ground truth, refusals that move nothing, stop, dead-man, protective stop, SSE,
frames, metrics."""

from __future__ import annotations

import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import pytest
from fastapi.testclient import TestClient
from scipy.spatial.transform import Rotation

from api.app import create_app
from cell.service import Cell
from cell.vision.frames import approach_tcp
from estimator.transforms import T_from_pose, T_from_pose_dict, make_T, pose_dict, pose_distance
from tests.support.cell import AUTH, running_cell, settled_tcp, sim_config, tcp, world
from tests.support.jobs import wait_job

OP, PLC, VIEW = AUTH["operator"], AUTH["plc"], AUTH["viewer"]
FLAT = np.array([[1.0, 0, 0], [0, -1, 0], [0, 0, -1]])  # plate facing up, +z into it
HOME_TARGET = (-480.0, -100.0, 0.0)


@pytest.fixture
def client(tmp_path: Path) -> Iterator[TestClient]:
    config = sim_config(tmp_path, limits={"max_pose_age_s": 1.0},
                        approach={"speed_mm_s": 250.0, "accel_mm_s2": 1200.0},
                        api={"image_log_dir": str(tmp_path / "imagelog"), "image_log_max": 2})
    with running_cell(config) as cell, TestClient(create_app(cell)) as c:
        yield c


def cell_of(client: TestClient) -> Cell:
    cell: Cell = client.app.state.cell  # type: ignore[attr-defined]
    return cell


def place(client: TestClient, T: np.ndarray) -> None:
    r = client.put("/api/v1/sim/target", json=pose_dict(T), headers=OP)
    assert r.status_code == 200, r.text


def random_placement(rng: np.random.Generator, yaw_fraction: float = 1.0) -> np.ndarray:
    tilt_axis = np.array([*rng.normal(size=2), 0.0])
    tilt = Rotation.from_rotvec(tilt_axis / np.linalg.norm(tilt_axis)
                                * np.radians(rng.uniform(0, 30)))
    yaw = Rotation.from_rotvec([0, 0, rng.uniform(-np.pi, np.pi) * yaw_fraction])
    R = (tilt * yaw).as_matrix() @ FLAT
    # keep the plate centre under the home camera
    offset = np.array([48.0, -32.0, 0.0])
    offset[:2] += rng.uniform(-40, 40, 2)
    offset[2] += rng.uniform(0, 40)
    centre = np.array(HOME_TARGET) + offset
    return make_T(R, centre - R @ np.array([48.0, 32.0, 0.0]))


def assert_not_moved(client: TestClient, before: np.ndarray) -> None:
    time.sleep(0.3)
    d_mm, d_deg = pose_distance(tcp(cell_of(client)), before)
    assert d_mm < 0.01 and d_deg < 0.01, f"the arm moved {d_mm:.3f} mm / {d_deg:.3f} deg"


def error_code(r: Any) -> str:
    return str(r.json()["error"]["code"])


def test_locate_random_placements_within_tolerance(client: TestClient) -> None:
    rng = np.random.default_rng(7)
    worst = [0.0, 0.0]
    for _ in range(6):
        T_true = random_placement(rng)
        place(client, T_true)
        time.sleep(0.15)  # a frame rendered with the new target
        r = client.post("/api/v1/locate", json={"n_frames": 2}, headers=PLC)
        assert r.status_code == 200, r.text
        body = r.json()
        d_mm, d_deg = pose_distance(T_from_pose_dict(body["T_base_target"]), T_true)
        worst = [max(worst[0], d_mm), max(worst[1], d_deg)]
        assert body["quality"]["rms_px"] < 0.5 and body["quality"]["frame_age_s"] < 1.0
    print(f"locate worst error: {worst[0]:.3f} mm / {worst[1]:.3f} deg")
    assert worst[0] <= 0.5 and worst[1] <= 0.1


def test_locate_right_after_the_part_moved_sees_it_where_it_lies(client: TestClient) -> None:
    """A PLC that puts a part down and asks at once: no frame from before the request."""
    rng = np.random.default_rng(3)
    for _ in range(8):
        T_true = random_placement(rng)
        place(client, T_true)
        r = client.post("/api/v1/locate", json={"n_frames": 2}, headers=PLC)
        assert r.status_code == 200, r.text
        d_mm, d_deg = pose_distance(T_from_pose_dict(r.json()["T_base_target"]), T_true)
        assert d_mm <= 0.5 and d_deg <= 0.1, f"{d_mm:.2f} mm / {d_deg:.3f} deg from the truth"


def test_approach_random_placements_reach_the_true_goal(client: TestClient) -> None:
    rng = np.random.default_rng(11)
    cell = cell_of(client)
    tool_poses = [None, {"position_mm": [5.0, -5.0, 0.0], "rotvec_rad": [0.0, 0.0, 0.5]}]
    for T_target_tcp in tool_poses:
        T_true = random_placement(rng, yaw_fraction=0.2)  # big yaws only cost time
        place(client, T_true)
        time.sleep(0.15)
        r = client.post("/api/v1/approach", json={"standoff_mm": 40, "wait": True,
                                                  "T_target_tcp": T_target_tcp}, headers=PLC)
        assert r.status_code == 200, r.text
        job = r.json()
        assert job["state"] == "succeeded", (job["error"], job["progress"])
        result = job["result"]
        assert 1 <= len(result["cycles"]) <= cell.config.approach.max_cycles
        assert all("correction_mm" in c for c in result["cycles"])
        T_tt = np.eye(4) if T_target_tcp is None else T_from_pose_dict(T_target_tcp)
        true_goal = approach_tcp(T_true, T_tt, 40.0)
        d_mm, d_deg = pose_distance(tcp(cell), true_goal)
        print(f"approach: {len(result['cycles'])} cycles, final error {d_mm:.3f} mm / "
              f"{d_deg:.3f} deg, estimated {result['estimated_error_mm']:.3f} mm")
        assert d_mm <= 0.3 and d_deg <= 0.1
        # back to where the camera sees the next placement
        r = client.post("/api/v1/jog", json={"mode": "step", "translation_mm": [0, 0, 150],
                                             "speed_mm_s": 100}, headers=OP)
        assert r.status_code == 200, r.text


def test_refusals_move_nothing(client: TestClient) -> None:
    cell = cell_of(client)
    before = tcp(cell)
    # auth
    assert client.get("/api/v1/status").status_code == 401
    r = client.post("/api/v1/approach", json={}, headers={"Authorization": "Bearer nope"})
    assert r.status_code == 401 and error_code(r) == "unauthorized"
    r = client.post("/api/v1/approach", json={}, headers=VIEW)
    assert r.status_code == 403 and error_code(r) == "forbidden"
    r = client.post("/api/v1/jog", json={"mode": "step", "translation_mm": [0, 0, 5]},
                    headers=PLC)
    assert r.status_code == 403
    # malformed bodies
    for body in ({"standoff_mm": "far"}, {"standoff_mm": -5}, {"speed_mm_s": 0},
                 {"T_target_tcp": {"position_mm": [0, 0]}}, {"bogus": 1}):
        r = client.post("/api/v1/approach", json=body, headers=PLC)
        assert r.status_code == 422 and error_code(r) == "invalid_request", body
    r = client.post("/api/v1/approach", content=b"{not json", headers={
        **PLC, "Content-Type": "application/json"})
    assert r.status_code == 422
    # speed above the cap
    r = client.post("/api/v1/approach", json={"speed_mm_s": 1000}, headers=PLC)
    assert r.status_code == 422 and error_code(r) == "speed_limit"
    # outside the envelope: the goal would be below the box floor
    place(client, T_from_pose([-480, -100, -60], [np.pi, 0, 0]))
    time.sleep(0.15)
    r = client.post("/api/v1/approach", json={"standoff_mm": 10}, headers=PLC)
    assert r.status_code == 422 and error_code(r) == "outside_envelope", r.text
    r = client.post("/api/v1/jog", json={"mode": "step", "translation_mm": [0, 0, -600]},
                    headers=OP)
    assert r.status_code == 422
    # stale pose: the last locate is older than limits.max_pose_age_s
    place(client, T_from_pose(HOME_TARGET, [np.pi, 0, 0]))
    time.sleep(0.15)
    assert client.post("/api/v1/locate", headers=PLC).status_code == 200
    time.sleep(1.2)
    r = client.post("/api/v1/approach", json={"use_last_locate": True}, headers=PLC)
    assert r.status_code == 409 and error_code(r) == "stale_pose"
    # unknown job
    r = client.get("/api/v1/jobs/nope", headers=VIEW)
    assert r.status_code == 404 and error_code(r) == "job_not_found"
    assert_not_moved(client, before)
    audit = client.get("/api/v1/audit", headers=VIEW).json()["entries"]
    outcomes = {e["outcome"] for e in audit}
    assert {"refused:outside_envelope", "refused:stale_pose", "refused:speed_limit"} <= outcomes


def test_camera_lost_refuses_approach_but_jogging_works(client: TestClient) -> None:
    cell = cell_of(client)
    before = tcp(cell)
    world(cell).set_camera_lost(True)
    r = client.post("/api/v1/approach", json={}, headers=PLC)
    assert r.status_code == 503 and error_code(r) == "camera_lost"
    r = client.post("/api/v1/locate", headers=PLC)
    assert r.status_code == 503
    assert_not_moved(client, before)
    r = client.post("/api/v1/jog", json={"mode": "step", "translation_mm": [0, 0, 10]},
                    headers=OP)
    assert r.status_code == 200, r.text
    assert tcp(cell)[2, 3] == pytest.approx(before[2, 3] + 10, abs=0.05)
    world(cell).set_camera_lost(False)


def test_busy_stop_during_approach_and_protective_stop(client: TestClient) -> None:
    cell = cell_of(client)
    r = client.post("/api/v1/approach", json={"standoff_mm": 40}, headers=PLC)
    assert r.status_code == 200, r.text
    job_id = r.json()["id"]
    assert r.json()["state"] == "running"
    time.sleep(0.3)
    r = client.post("/api/v1/approach", json={}, headers=PLC)
    assert r.status_code == 409 and error_code(r) == "busy"
    r = client.post("/api/v1/jog", json={"mode": "continuous", "linear_mm_s": [0, 0, 10]},
                    headers=OP)
    assert r.status_code == 409 and error_code(r) == "busy"
    status = client.get("/api/v1/status", headers=PLC).json()
    assert status["state"] == "approach" and status["job"]["id"] == job_id
    r = client.post("/api/v1/stop", headers=VIEW)  # every valid token may stop
    assert r.status_code == 200 and r.json()["job_id"] == job_id
    job = wait_job(client, job_id)
    assert job["state"] == "cancelled"
    settled_tcp(cell)
    # a protective stop in the middle of an approach fails the job with the reason
    r = client.post("/api/v1/approach", json={"standoff_mm": 40}, headers=PLC)
    assert r.status_code == 200, r.text
    job_id = r.json()["id"]
    start = tcp(cell)
    deadline = time.monotonic() + 5.0
    while pose_distance(tcp(cell), start)[0] < 2.0:  # so that the stop lands mid-motion
        assert time.monotonic() < deadline
        time.sleep(0.01)
    world(cell).trigger_protective_stop("test: collision")
    job = wait_job(client, job_id)
    assert job["state"] == "failed" and job["error"]["code"] == "protective_stop", job
    assert "safety stop" in job["error"]["message"]
    # and then nothing moves until it is cleared
    held = settled_tcp(cell)
    for path, body, hdr in (("/api/v1/approach", {}, PLC),
                            ("/api/v1/jog", {"mode": "step", "translation_mm": [0, 0, 5]}, OP)):
        r = client.post(path, json=body, headers=hdr)
        assert r.status_code == 409 and error_code(r) == "protective_stop", r.text
    assert_not_moved(client, held)
    assert client.get("/api/v1/status", headers=VIEW).json()["state"] == "protective_stop"


def _jog_end_reason(client: TestClient) -> str:
    end = next(e for e in client.get("/api/v1/audit", headers=VIEW).json()["entries"]
               if e["command"] == "jog_end")
    return str(end["detail"])


def _hold_jog(client: TestClient, hold_s: float, deadman_s: float) -> float | None:
    """Start a continuous jog up and beat its dead-man for ``hold_s``; the time of the last
    heartbeat, or None when the dead-man fired because this host let a heartbeat go out later
    than the dead-man period (the product's right answer to a late heartbeat)."""
    r = client.post("/api/v1/jog", json={"mode": "continuous", "frame": "base",
                                         "linear_mm_s": [0, 0, 40]}, headers=OP)
    assert r.status_code == 200, r.text
    t_end = time.monotonic() + hold_s
    sent_ok = time.monotonic()
    while True:
        sent = time.monotonic()
        r = client.post("/api/v1/jog/heartbeat", headers=OP)
        if r.status_code != 200:
            late_s = time.monotonic() - sent_ok  # at least the gap the service saw
            reason = _jog_end_reason(client)
            assert "dead-man" in reason and late_s > deadman_s, (r.text, reason, late_s)
            return None
        sent_ok, last_beat = sent, time.time()
        if time.monotonic() > t_end:
            return last_beat
        time.sleep(0.02)  # well inside the 200 ms dead-man period, also on a loaded host


def test_continuous_jog_with_dead_man(client: TestClient) -> None:
    cell = cell_of(client)
    deadman_s = cell.config.limits.deadman_timeout_s
    r = client.post("/api/v1/jog/heartbeat", headers=OP)
    assert r.status_code == 409 and error_code(r) == "not_jogging"
    for _ in range(3):
        z0 = settled_tcp(cell, timeout_s=1.5)[2, 3]
        last_beat = _hold_jog(client, 1.0, deadman_s)
        if last_beat is not None:
            break
    assert last_beat is not None, "every try had a heartbeat later than the dead-man period"
    # no more heartbeats: the dead-man stops the jog
    deadline = time.monotonic() + 3.0
    while client.get("/api/v1/status", headers=VIEW).json()["state"] == "jog":
        assert time.monotonic() < deadline
        time.sleep(0.02)
    end = next(e for e in client.get("/api/v1/audit", headers=VIEW).json()["entries"]
               if e["command"] == "jog_end")
    assert "dead-man" in end["detail"]
    stop_delay = end["ended_at"] - last_beat
    print(f"dead-man stop {stop_delay * 1000:.0f} ms after the last heartbeat")
    assert stop_delay < 0.25 + 0.15  # 250 ms budget, margin for a loaded CI machine
    rise = settled_tcp(cell, timeout_s=1.5)[2, 3] - z0  # at rest well within 1.5 s
    assert 25 < rise < 60, rise  # ~1.1 s at 40 mm/s
    r = client.post("/api/v1/jog", json={"mode": "continuous", "linear_mm_s": [0, 0, 500]},
                    headers=OP)
    assert r.status_code == 422 and error_code(r) == "jog_speed_limit"


def test_events_frame_metrics_health_and_roles(client: TestClient) -> None:
    assert client.get("/api/v1/health").json()["status"] == "ok"
    me = client.get("/api/v1/me", headers=PLC).json()
    assert me["role"] == "plc" and "approach" in me["permissions"] and "jog" not in \
        me["permissions"]
    with client.stream("GET", "/api/v1/events?max_events=3", headers=VIEW) as r:
        assert r.status_code == 200
        text = "".join(r.iter_text())
    assert text.count("event: state") == 3 and "T_base_tcp" in text
    r = client.get("/api/v1/camera/frame.png?overlay=true", headers=VIEW)
    assert r.status_code == 200 and r.headers["content-type"] == "image/png"
    img = cv2.imdecode(np.frombuffer(r.content, np.uint8), cv2.IMREAD_COLOR)
    assert img is not None and img.shape == (800, 1280, 3)
    green = (img[:, :, 1] > 200) & (img[:, :, 0] < 80) & (img[:, :, 2] < 80)
    assert green.sum() > 200  # detections drawn
    r = client.get("/api/v1/camera/frame.png", params={"token": "sim-viewer"})
    assert r.status_code == 200
    grey = cv2.imdecode(np.frombuffer(r.content, np.uint8), cv2.IMREAD_UNCHANGED)
    assert grey is not None and grey.ndim == 2
    truth = client.get("/api/v1/sim/truth", headers=VIEW).json()
    assert np.allclose(truth["T_base_target"]["position_mm"], HOME_TARGET)
    assert client.put("/api/v1/sim/target", json=truth["T_base_target"],
                      headers=PLC).status_code == 403
    metrics = client.get("/metrics", headers=VIEW).text
    assert 'cell_http_request_duration_seconds_count{method="GET",route="/api/v1/sim/truth",' \
        'status="200"} 1.0' in metrics
    assert "cell_arm_connected 1.0" in metrics
    assert 'cell_stalls_total{by="host"}' in metrics and 'cell_stalls_total{by="own"}' in metrics
    assert client.get("/metrics").status_code == 401


def test_failed_locates_go_to_the_image_log(client: TestClient) -> None:
    cell = cell_of(client)
    place(client, T_from_pose([-480, 300, 0], [np.pi, 0, 0]))  # out of view
    time.sleep(0.15)
    for _ in range(3):
        r = client.post("/api/v1/locate", headers=PLC)
        assert r.status_code == 409, r.text
        assert error_code(r) in ("too_few_blobs", "no_correspondence")
        assert "target not located" in r.json()["error"]["message"]
    assert cell.image_log is not None
    entries = cell.image_log.entries()
    assert len(entries) == 2  # a bounded ring
    img = cv2.imread(str(entries[-1]), cv2.IMREAD_UNCHANGED)
    assert img is not None and img.shape == (800, 1280)
    assert "code" in entries[-1].with_suffix(".json").read_text()
    metrics = client.get("/metrics", headers=VIEW).text
    assert 'cell_locate_total{outcome="failed"} 3.0' in metrics
