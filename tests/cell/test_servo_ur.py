"""Closed-loop servoing end to end over HTTP, on the simulated cell through ur_rtde: servo
approach from random placements, tracking a moving target, a covered lens, a stop and a limit
reached mid-servo (nothing outside the envelope is ever commanded)."""

from __future__ import annotations

import time
from collections.abc import Iterator
from typing import Any

import numpy as np
import pytest
from fastapi.testclient import TestClient
from scipy.spatial.transform import Rotation

from api.app import create_app
from cell.service import Cell
from cell.vision.frames import approach_tcp
from estimator.transforms import make_T, pose_dict, pose_distance
from fakes.ur_controller.process import free_loopback_host
from tests.support.cell import AUTH, running_cell, sim_config, world
from tests.support.jobs import wait_job

HOME_TARGET = make_T(Rotation.from_rotvec([np.pi, 0, 0]).as_matrix(),
                     np.array([-480.0, -100.0, 0.0]))


@pytest.fixture(scope="module")
def client(tmp_path_factory: pytest.TempPathFactory) -> Iterator[TestClient]:
    # lost_after_s 1 s rather than the default 0.1: this 2-core machine runs other engineers'
    # suites too, and there the adapter's pose history has been seen to stall for 0.8 s (a
    # frame it cannot pair with a pose is no pose); the covered-lens test needs no tight value
    config = sim_config(tmp_path_factory.mktemp("servo"), robot="ur", host=free_loopback_host(),
                        servo={"lost_after_s": 1.0})
    with running_cell(config) as cell, TestClient(create_app(cell)) as c:
        yield c


def _cell(client: TestClient) -> Cell:
    cell: Cell = client.app.state.cell  # type: ignore[attr-defined]
    return cell


def _place(client: TestClient, T: np.ndarray, velocity_mm_s: list[float] | None = None) -> None:
    body: dict[str, Any] = dict(pose_dict(T))
    if velocity_mm_s is not None:
        body["velocity_mm_s"] = velocity_mm_s
    r = client.put("/api/v1/sim/target", json=body, headers=AUTH["operator"])
    assert r.status_code == 200, r.text


@pytest.fixture
def home(client: TestClient) -> Iterator[None]:
    world(_cell(client)).set_camera_blocked(False)
    _place(client, HOME_TARGET)
    r = client.post("/api/v1/arm/home", json={"wait": True}, headers=AUTH["operator"])
    assert r.status_code == 200 and r.json()["state"] == "succeeded", r.text
    yield
    world(_cell(client)).set_camera_blocked(False)
    client.post("/api/v1/stop", headers=AUTH["viewer"])


def _still(cell: Cell) -> bool:
    """The true TCP does not move over 100 ms."""
    a = world(cell).true_T_base_tcp()
    time.sleep(0.1)
    return pose_distance(a, world(cell).true_T_base_tcp())[0] < 0.01


def _servo_commands_inside(cell: Cell, since_s: float) -> int:
    guard = cell.arm.guard
    n = 0
    for c in cell.commanded():
        if c.kind != "servo" or c.t_s < since_s:
            continue
        assert c.T_base_tcp is not None and c.T_from is not None
        for T in (c.T_from, c.T_base_tcp, *c.path):
            assert guard.box_violation_mm(T[:3, 3]) == 0.0, T[:3, 3]
            assert guard.tilt_excess_deg(T) == 0.0
        n += 1
    return n


@pytest.mark.parametrize("seed", [11, 12])
def test_servo_approach_from_random_placements(client: TestClient, home: None,
                                               seed: int) -> None:
    cell = _cell(client)
    rng = np.random.default_rng(seed)
    R = Rotation.from_rotvec(np.radians([*rng.uniform(-4, 4, 2), rng.uniform(-20, 20)]))
    T_true = make_T(R.as_matrix() @ HOME_TARGET[:3, :3],  # turned about its own origin
                    HOME_TARGET[:3, 3] + np.r_[rng.uniform(-40, 40, 2), 0.0])
    _place(client, T_true)
    t0 = time.monotonic()
    r = client.post("/api/v1/approach", json={"standoff_mm": 50, "mode": "servo", "wait": True},
                    headers=AUTH["plc"])
    assert r.status_code == 200, r.text
    job = r.json()
    assert job["state"] == "succeeded", job["error"]
    res = job["result"]
    assert res["mode"] == "servo" and res["converged"]
    assert 0 < res["time_to_converge_s"] < 30 and 2 <= len(res["error_history"]) <= 100
    time.sleep(0.2)
    d_mm, d_deg = pose_distance(world(cell).true_T_base_tcp(), approach_tcp(T_true, np.eye(4), 50))
    print(f"servo approach: {res['time_to_converge_s']:.2f} s, true error {d_mm:.3f} mm / "
          f"{d_deg:.3f} deg, estimated {res['estimated_error_mm']:.3f} mm")
    assert d_mm <= 0.3 and d_deg <= 0.1
    assert _servo_commands_inside(cell, t0) > 50


def test_track_a_moving_target_then_stop(client: TestClient, home: None) -> None:
    cell = _cell(client)
    r = client.post("/api/v1/track", json={"standoff_mm": 50, "duration_s": 30},
                    headers=AUTH["plc"])
    assert r.status_code == 200, r.text
    job_id = r.json()["id"]
    deadline = time.monotonic() + 15
    while True:  # converge on the still target first
        T_tcp, t = world(cell).true_tcp_sample()
        if pose_distance(T_tcp, approach_tcp(world(cell).true_T_base_target(t), np.eye(4),
                                             50))[0] < 1.0:
            break
        assert time.monotonic() < deadline
        time.sleep(0.05)
    _place(client, world(cell).true_T_base_target(), velocity_mm_s=[30.0, 0.0, 0.0])
    t_move = time.monotonic()
    errors = []
    while time.monotonic() < t_move + 3.0:
        T_tcp, t = world(cell).true_tcp_sample()
        if t > t_move + 1.5:
            errors.append(pose_distance(T_tcp, approach_tcp(world(cell).true_T_base_target(t),
                                                            np.eye(4), 50))[0])
        time.sleep(0.03)
    moved = world(cell).true_T_base_tcp()[0, 3] - HOME_TARGET[0, 3]
    print(f"tracking at 30 mm/s: median error {np.median(errors):.3f} mm, max {max(errors):.3f}")
    assert moved > 50  # the arm went along
    assert np.median(errors) < 5.0  # accuracy is the benchmark's business (cell bench approach)
    r = client.post("/api/v1/stop", headers=AUTH["plc"])
    assert r.status_code == 200 and r.json()["job_id"] == job_id
    job = wait_job(client, job_id, 10)
    assert job["state"] == "cancelled"
    _place(client, world(cell).true_T_base_target())  # the conveyor stops too
    assert _still(cell)


def test_target_covered_mid_servo_ends_target_lost_with_the_arm_still(
        client: TestClient, home: None) -> None:
    cell = _cell(client)
    r = client.post("/api/v1/approach", json={"standoff_mm": 50, "mode": "servo"},
                    headers=AUTH["plc"])
    assert r.status_code == 200, r.text
    time.sleep(1.0)  # mid-approach, the arm moving fast
    world(cell).set_camera_blocked(True)
    job = wait_job(client, r.json()["id"], 10)
    assert job["state"] == "failed" and job["error"]["code"] == "target_lost", job
    assert job["progress"]["stopped_in_ms"] < 1000
    assert _still(cell)
    assert not cell.arm.state().moving


def test_stop_mid_servo_halts_at_once(client: TestClient, home: None) -> None:
    cell = _cell(client)
    r = client.post("/api/v1/approach", json={"standoff_mm": 50, "mode": "servo"},
                    headers=AUTH["plc"])
    assert r.status_code == 200, r.text
    time.sleep(1.0)
    s = client.post("/api/v1/stop", headers=AUTH["viewer"])
    t_stop = time.monotonic()  # the stop answered: on a loaded host later than it was sent
    assert s.status_code == 200 and s.json()["cancelled"] == "approach"
    job = wait_job(client, r.json()["id"], 10)
    assert job["state"] == "cancelled"
    assert _still(cell)
    late = [c for c in cell.commanded() if c.kind == "servo" and c.t_s > t_stop + 0.05]
    assert not late  # no tick passed the guard after the stop


def test_limit_reached_mid_servo_ends_with_its_code_inside_the_envelope(
        client: TestClient, home: None) -> None:
    cell = _cell(client)
    t0 = time.monotonic()
    r = client.post("/api/v1/track", json={"standoff_mm": 50, "duration_s": 30},
                    headers=AUTH["operator"])
    assert r.status_code == 200, r.text
    time.sleep(2.5)
    # the part sinks: 50 mm above it is soon below the box floor (z = 20 mm)
    _place(client, world(cell).true_T_base_target(), velocity_mm_s=[0.0, 0.0, -40.0])
    job = wait_job(client, r.json()["id"], 15)
    _place(client, world(cell).true_T_base_target())
    assert job["state"] == "failed" and job["error"]["code"] == "outside_envelope", job
    assert _still(cell)
    assert world(cell).true_T_base_tcp()[2, 3] >= cell.config.limits.workspace_min_mm[2]
    assert _servo_commands_inside(cell, t0) > 50
