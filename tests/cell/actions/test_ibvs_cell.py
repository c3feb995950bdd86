"""IBVS on the simulated cell over HTTP: teach a view, move away, approach it image-based and
end near the simulator's truth; the mode refused with typed errors (nothing moves); a hidden
dot is dropped and the loop goes on; too few dots stop the arm with ``target_lost``."""

from __future__ import annotations

import time
from collections.abc import Iterator
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from fastapi.testclient import TestClient

from api.app import create_app
from cell.features.teach import TaughtPose, TaughtStore
from cell.service import Cell
from estimator.transforms import pose_distance
from tests.support.cell import AUTH, running_cell, sim_config, tcp

OP, PLC = AUTH["operator"], AUTH["plc"]


@pytest.fixture
def client(tmp_path: Path) -> Iterator[TestClient]:
    # a loaded host delays frames: the lost-target clock is generous here (its own tests are
    # elsewhere); the hidden-dots case below still ends target_lost
    config = sim_config(tmp_path, servo={"lost_after_s": 1.0})
    with running_cell(config) as cell, TestClient(create_app(cell)) as c:
        yield c


def cell_of(client: TestClient) -> Cell:
    cell: Cell = client.app.state.cell  # type: ignore[attr-defined]
    return cell


def jog(client: TestClient, translation_mm: list[float], rotation_deg: list[float]) -> None:
    r = client.post("/api/v1/jog", json={"mode": "step", "translation_mm": translation_mm,
                                         "rotation_deg": rotation_deg, "speed_mm_s": 100},
                    headers=OP)
    assert r.status_code == 200, r.text
    time.sleep(0.2)


def teach_here(client: TestClient, name: str = "view") -> dict[str, Any]:
    r = client.post("/api/v1/teach", json={"name": name, "samples": 8}, headers=OP)
    assert r.status_code == 200, r.text
    return dict(r.json())


def approach_ibvs(client: TestClient, name: str = "view") -> dict[str, Any]:
    r = client.post("/api/v1/approach", json={"taught": name, "mode": "ibvs", "wait": True},
                    headers=PLC)
    assert r.status_code == 200, r.text
    return dict(r.json())


def test_teach_records_the_view_and_ibvs_returns_to_it(client: TestClient) -> None:
    cell = cell_of(client)
    time.sleep(0.2)
    T_taught = tcp(cell)
    taught = teach_here(client)
    view = taught["view"]
    assert view["ids"] == list(range(6)) and len(view["xy"]) == 6
    assert all(300 < z < 700 for z in view["depth_mm"])
    jog(client, [20.0, -12.0, 8.0], [0.0, 2.0, 4.0])
    assert pose_distance(tcp(cell), T_taught)[0] > 15
    job = approach_ibvs(client)
    assert job["state"] == "succeeded", job["error"]
    res = job["result"]
    assert res["mode"] == "ibvs" and res["converged"] is True
    d_mm, d_deg = pose_distance(tcp(cell), T_taught)
    print(f"ibvs: {d_mm:.3f} mm / {d_deg:.4f} deg from the taught truth, image error "
          f"{res['image_error_px_rms']:.4f} px RMS, estimated {res['estimated_error_mm']:.3f} mm")
    # the view's weak direction (a turn about a point near the target) is below a frame's
    # noise: the figure benchmarks measure; here, that the loop closed on the taught view
    assert d_mm < 1.0 and d_deg < 0.2
    assert res["image_error_px_rms"] < cell.config.ibvs.tolerance_px_rms
    assert res["image_error_px_max"] < cell.config.ibvs.tolerance_px_max
    assert np.isfinite(res["estimated_error_mm"]) and np.isfinite(res["estimated_error_deg"])
    assert res["min_dots_used"] == 6 and res["min_dot_border_px"] > 0


def test_ibvs_refusals_are_typed_and_move_nothing(client: TestClient, tmp_path: Path) -> None:
    cell = cell_of(client)
    time.sleep(0.2)
    before = tcp(cell)
    r = client.post("/api/v1/approach", json={"mode": "ibvs", "wait": True}, headers=PLC)
    assert r.status_code == 422 and r.json()["error"]["code"] == "ibvs_needs_taught"
    r = client.post("/api/v1/approach", json={"mode": "ibvs", "taught": "nope"}, headers=PLC)
    assert r.status_code == 404 and r.json()["error"]["code"] == "taught_not_found"
    r = client.post("/api/v1/approach", json={"mode": "bogus"}, headers=PLC)
    assert r.status_code == 422 and r.json()["error"]["code"] == "invalid_request"
    taught = teach_here(client, "fresh")
    assert taught["view"] is not None
    r = client.post("/api/v1/approach", json={"mode": "ibvs", "taught": "fresh",
                                              "standoff_mm": 30}, headers=PLC)
    assert r.status_code == 422 and r.json()["error"]["code"] == "invalid_standoff"
    r = client.post("/api/v1/track", json={"mode": "ibvs", "standoff_mm": 0,
                                           "duration_s": 1}, headers=PLC)
    assert r.status_code == 422 and r.json()["error"]["code"] == "ibvs_needs_taught"
    # a pose taught before views were recorded: servo and look-and-move only
    store = cell.taught
    old: TaughtPose = replace(store.get("fresh"), name="old", view=None)
    store.put(old)
    text = (tmp_path / "taught_poses.json").read_text()
    assert '"view": null' in text
    assert TaughtStore(tmp_path / "taught_poses.json").get("old").view is None
    for path in ("/api/v1/approach", "/api/v1/track"):
        r = client.post(path, json={"mode": "ibvs", "taught": "old", "standoff_mm": 0,
                                    "duration_s": 1}
                        if path.endswith("track") else {"mode": "ibvs", "taught": "old"},
                        headers=PLC)
        assert r.status_code == 422 and r.json()["error"]["code"] == "taught_without_view"
        assert "teach it again" in r.json()["error"]["message"]
    time.sleep(0.2)
    d_mm, d_deg = pose_distance(tcp(cell), before)
    assert d_mm < 0.01 and d_deg < 0.01
    r = client.post("/api/v1/approach", json={"taught": "old", "standoff_mm": 0,
                                              "mode": "look_and_move", "wait": True},
                    headers=PLC)
    assert r.status_code == 200 and r.json()["state"] == "succeeded", r.text


def _hide(cell: Cell, monkeypatch: pytest.MonkeyPatch, hidden: set[int]) -> None:
    """The estimator reports the dots in ``hidden`` as not matched (occluded or outside the
    image): the matched ids and image points it returns leave them out (every frame the
    locator estimates: the approach's first locate, whose frame the loop starts from, too)."""
    locator = cell.core.locator
    original = locator._estimate

    def estimate(frame: Any, *args: Any) -> Any:
        result = original(frame, *args)
        keep = [k for k, i in enumerate(result.matched_ids) if i not in hidden]
        return replace(result, matched_ids=tuple(result.matched_ids[k] for k in keep),
                       image_points_px=result.image_points_px[keep])

    monkeypatch.setattr(locator, "_estimate", estimate)


def test_a_hidden_dot_drops_out_and_too_few_stop_the_arm(
        client: TestClient, monkeypatch: pytest.MonkeyPatch) -> None:
    cell = cell_of(client)
    time.sleep(0.2)
    T_taught = tcp(cell)
    teach_here(client)
    jog(client, [15.0, 10.0, -8.0], [0.0, 0.0, -4.0])
    _hide(cell, monkeypatch, {2})
    job = approach_ibvs(client)
    assert job["state"] == "succeeded", job["error"]
    res = job["result"]
    assert res["min_dots_used"] == 5 and res["frames_missing_dots"] == res["frames"]
    d_mm, d_deg = pose_distance(tcp(cell), T_taught)
    assert d_mm < 1.0 and d_deg < 0.2

    jog(client, [10.0, 0.0, 0.0], [0.0, 0.0, 0.0])
    _hide(cell, monkeypatch, {0, 2, 4})
    job = approach_ibvs(client)
    assert job["state"] == "failed" and job["error"]["code"] == "target_lost"
    assert "3 of the taught view's dots" in job["error"]["message"]
    time.sleep(0.2)
    assert not cell.arm_state().moving


def test_track_in_ibvs_mode_holds_the_taught_view(client: TestClient) -> None:
    cell = cell_of(client)
    time.sleep(0.2)
    T_taught = tcp(cell)
    teach_here(client)
    jog(client, [8.0, -6.0, 4.0], [0.0, 0.0, 2.0])
    r = client.post("/api/v1/track", json={"taught": "view", "mode": "ibvs", "standoff_mm": 0,
                                           "duration_s": 4.0, "wait": True}, headers=PLC)
    assert r.status_code == 200, r.text
    job = r.json()
    assert job["state"] == "succeeded", job["error"]
    assert job["params"]["mode"] == "ibvs" and job["result"]["mode"] == "ibvs_track"
    d_mm, d_deg = pose_distance(tcp(cell), T_taught)
    assert d_mm < 1.0 and d_deg < 0.2


def test_the_settle_steps_from_a_still_view_and_ends_near_the_truth(tmp_path: Path) -> None:
    """With ``[ibvs] settle_frames`` the approach stops, averages the still view and steps;
    the result lists each window's step and the arm ends near the taught truth (the figures
    are the benchmark's: from this 456 mm view the image resolves ~0.1-0.2 mm)."""
    config = sim_config(tmp_path, servo={"lost_after_s": 1.0},
                        ibvs={"settle_frames": 8, "settle_steps": 2})
    with running_cell(config) as cell, TestClient(create_app(cell)) as client:
        time.sleep(0.2)
        T_taught = tcp(cell)
        teach_here(client)
        jog(client, [-15.0, 10.0, 6.0], [1.0, 0.0, -3.0])
        job = approach_ibvs(client)
        assert job["state"] == "succeeded", job["error"]
        steps = job["result"]["settle_steps_mm_deg"]
        assert 1 <= len(steps) <= 2 and all(len(s) == 2 and s[0] >= 0 for s in steps)
        assert steps[0][0] < 1.0  # the loop had already brought the view close
        # each step averaged its still frames only: carrying the loop's last is off by default
        frames = job["result"]["settle_frames_still_carried"]
        assert len(frames) == len(steps) and all(f == [8, 0] for f in frames)
        d_mm, d_deg = pose_distance(tcp(cell), T_taught)
        print(f"ibvs with settle: {d_mm:.3f} mm / {d_deg:.4f} deg, steps {steps}")
        assert d_mm < 1.0 and d_deg < 0.2
        assert not cell.arm_state().moving
