"""Links that come back, recovery routes and motion end from the controller, over HTTP on the
simulated cell through the real UR adapter and ur_rtde (the controller in its own process)."""

from __future__ import annotations

import multiprocessing
import threading
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import numpy as np
from fastapi.testclient import TestClient

from api.app import create_app
from cell.service import Cell
from estimator.transforms import pose_distance
from fakes.ur_controller.process import free_loopback_host
from tests.support.cell import AUTH, running_cell, settled_tcp, sim_config, world
from tests.support.jobs import wait_job
from tests.support.waiting import wait_until

OP, PLC, VIEW = AUTH["operator"], AUTH["plc"], AUTH["viewer"]


@contextmanager
def ur_client(tmp_path: Path, **sim: Any) -> Iterator[TestClient]:
    config = sim_config(tmp_path, robot="ur", host=free_loopback_host(),
                        approach={"speed_mm_s": 250.0, "accel_mm_s2": 1500.0}, sim=sim)
    config = config.model_copy(update={"robot": config.robot.model_copy(
        update={"reconnect_max_s": 1.0})})
    with running_cell(config) as cell, TestClient(create_app(cell)) as c:
        yield c


def cell_of(client: TestClient) -> Cell:
    cell: Cell = client.app.state.cell  # type: ignore[attr-defined]
    return cell


def moving_away(cell: Cell, start: np.ndarray, mm: float, timeout_s: float = 10.0) -> None:
    wait_until(lambda: pose_distance(world(cell).true_T_base_tcp(), start)[0] > mm, timeout_s,
               "the arm to move")


def ready(client: TestClient) -> bool:
    """Linked, powered (the sim config powers on after a connect) and idle."""
    return bool(client.get("/api/v1/health").json()["status"] == "ok"
                and client.get("/api/v1/status", headers=VIEW).json()["state"] == "idle")


def approach_ok(client: TestClient) -> None:
    r = client.post("/api/v1/approach", json={"standoff_mm": 40, "wait": True}, headers=PLC)
    assert r.status_code == 200 and r.json()["state"] == "succeeded", r.text


def test_service_without_its_controller_serves_and_picks_it_up_again(tmp_path: Path) -> None:
    with ur_client(tmp_path, controller_running_at_start=False) as client:
        cell = cell_of(client)
        health = client.get("/api/v1/health")
        assert health.status_code == 200
        assert health.json()["status"] == "degraded" and "arm" in health.json()["missing"]
        status = client.get("/api/v1/status", headers=VIEW)
        assert status.status_code == 200 and status.json()["robot"]["connected"] is False
        r = client.post("/api/v1/approach", json={}, headers=PLC)
        assert r.status_code == 503 and r.json()["error"]["code"] in (
            "arm_disconnected", "camera_lost"), r.text
        # the controller boots after the cell PC
        world(cell).start_controller()
        wait_until(lambda: ready(client), 30.0, "the arm link")
        r = client.post("/api/v1/locate", headers=PLC)
        assert r.status_code == 200, r.text
        approach_ok(client)
        # killed mid-approach: the job fails with the reason; back without a restart
        r = client.post("/api/v1/arm/home", json={"wait": True}, headers=OP)
        assert r.status_code == 200 and r.json()["state"] == "succeeded", r.text
        r = client.post("/api/v1/approach", json={"standoff_mm": 40}, headers=PLC)
        assert r.status_code == 200, r.text
        moving_away(cell, world(cell).true_T_base_tcp(), 5.0)
        world(cell).kill_controller()
        job = wait_job(client, r.json()["id"], 20.0)
        assert job["state"] == "failed" and job["error"]["code"] == "arm_disconnected", job
        assert client.get("/api/v1/health").json()["missing"] == ["arm"]
        world(cell).start_controller()
        wait_until(lambda: ready(client), 30.0, "the arm link again")
        approach_ok(client)
        tries = [e for e in cell.jobs.audit_log(500) if e.command == "approach_end"]
        assert [e.outcome for e in tries][:3] == ["succeeded", "failed", "succeeded"]


def test_unlock_and_home_over_http(tmp_path: Path) -> None:
    with ur_client(tmp_path) as client:
        cell = cell_of(client)
        home = world(cell).true_T_base_tcp()
        r = client.post("/api/v1/jog", json={"mode": "step", "translation_mm": [40, 30, -30]},
                        headers=OP)
        assert r.status_code == 200, r.text
        world(cell).trigger_protective_stop("test")
        wait_until(lambda: client.get("/api/v1/status", headers=VIEW).json()["robot"][
            "protective_stop"], 5.0, "the protective stop")
        assert client.post("/api/v1/arm/unlock", headers=VIEW).status_code == 403
        r = client.post("/api/v1/arm/unlock", headers=OP)
        assert r.status_code == 409 and r.json()["error"]["code"] == "unlock_too_early", r.text
        assert "try again in" in r.json()["error"]["message"]
        r = client.post("/api/v1/arm/home", json={"wait": True}, headers=OP)
        assert r.status_code == 409 and r.json()["error"]["code"] == "protective_stop", r.text
        held = settled_tcp(cell)
        robot = client.get("/api/v1/status", headers=VIEW).json()["robot"]
        assert robot["protective_stop"] and not robot["moving"], robot
        time.sleep(5.0)
        r = client.post("/api/v1/arm/unlock", headers=OP)
        assert r.status_code == 200 and r.json()["unlocked"] and r.json()["ready"], r.text
        assert pose_distance(world(cell).true_T_base_tcp(), held)[0] < 0.01
        r = client.post("/api/v1/arm/home", json={"wait": True}, headers=OP)
        assert r.status_code == 200 and r.json()["state"] == "succeeded", r.text
        assert pose_distance(settled_tcp(cell), home)[0] < 0.5
        r = client.post("/api/v1/arm/power", json={"on": False}, headers=OP)
        assert r.status_code == 200 and r.json()["robot_mode"] == "POWER_OFF", r.text
        r = client.post("/api/v1/jog", json={"mode": "step", "translation_mm": [0, 0, 5]},
                        headers=OP)
        assert r.status_code == 409 and r.json()["error"]["code"] == "arm_not_ready", r.text
        r = client.post("/api/v1/arm/power", json={"on": True}, headers=OP)
        assert r.status_code == 200 and r.json()["ready"], r.text
        approach_ok(client)
        commands = [e.command for e in cell.jobs.audit_log(100)]
        assert {"unlock", "home", "power"} <= set(commands)


def test_a_frozen_controller_is_told_to_stop_first_when_it_answers_again(tmp_path: Path) -> None:
    """Frozen mid-approach and resumed, the controller is told to stop before the arm goes on
    (left alone it goes on 21-126 mm)."""
    with ur_client(tmp_path) as client:
        cell = cell_of(client)
        world(cell).set_target(np.asarray(world(cell).true_T_base_target()) @ np.array(
            [[1, 0, 0, 60.0], [0, 1, 0, 40.0], [0, 0, 1, 0], [0, 0, 0, 1]]))
        r = client.post("/api/v1/approach", json={"standoff_mm": 40, "speed_mm_s": 100},
                        headers=PLC)
        assert r.status_code == 200, r.text
        moving_away(cell, world(cell).true_T_base_tcp(), 5.0)
        world(cell).freeze_controller(True)
        try:
            job = wait_job(client, r.json()["id"], 10.0)
            assert job["state"] == "failed" and job["error"]["code"] == "arm_disconnected", job
            stop = client.post("/api/v1/stop", headers=PLC).json()
            assert stop["stopped"] is False and "before anything else" in stop["arm_error"]
            time.sleep(1.0)  # the cell is trying to reconnect meanwhile
        finally:
            world(cell).freeze_controller(False)
        resumed = time.monotonic()
        at_resume = world(cell).true_T_base_tcp()
        wait_until(lambda: ready(client), 30.0, "the arm link")
        still = settled_tcp(cell)
        moved_mm = pose_distance(still, at_resume)[0]
        print(f"after the resume the arm moved {moved_mm:.1f} mm and was still "
              f"{time.monotonic() - resumed:.2f} s later")
        assert moved_mm < 15.0
        approach_ok(client)


def _burn(stop: Any) -> None:
    x = 0
    while not stop.is_set():
        x = (x * 31 + 7) % 1000003


APPROACHES_LOADED = 6


def test_six_approaches_succeed_with_the_host_loaded(tmp_path: Path) -> None:
    """Motion end comes from the controller, not from a pose that stood still for 50 ms: two
    CPU burners and the live view polled at 10 Hz, 6 of 6 approaches must succeed (the burners
    load the whole host, so the run is kept short)."""
    stop_burn = multiprocessing.Event()
    burners = [multiprocessing.Process(target=_burn, args=(stop_burn,), daemon=True)
               for _ in range(2)]
    for p in burners:
        p.start()
    stop_poll = threading.Event()
    try:
        with ur_client(tmp_path) as client:
            def poll() -> None:
                while not stop_poll.wait(0.1):
                    client.get("/api/v1/camera/frame.png?overlay=true", headers=VIEW)

            poller = threading.Thread(target=poll, daemon=True)
            poller.start()
            outcomes = []
            t0 = time.monotonic()
            for k in range(APPROACHES_LOADED):
                standoff = 40.0 + 20.0 * (k % 2)  # alternate, so every approach really moves
                r = client.post("/api/v1/approach", json={"standoff_mm": standoff,
                                                          "wait": True}, headers=PLC)
                assert r.status_code == 200, r.text
                outcomes.append((r.json()["state"], r.json()["error"]))
            print(f"{APPROACHES_LOADED} approaches under load in {time.monotonic() - t0:.1f} s")
            stop_poll.set()
            poller.join(2.0)
            assert [s for s, _ in outcomes] == ["succeeded"] * APPROACHES_LOADED, outcomes
    finally:
        stop_burn.set()
        for p in burners:
            p.join(2.0)
            if p.is_alive():
                p.kill()
