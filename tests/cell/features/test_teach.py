"""Taught reference poses: the store (persistence, atomic writes, unreadable files), averaging
and its spread, and over HTTP on the simulated cell: teach, move away, approach by name."""

from __future__ import annotations

import json
import time
from collections.abc import Iterator
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from fastapi.testclient import TestClient
from scipy.spatial.transform import Rotation

from api.app import create_app
from cell.errors import CellError, LimitError, NotFoundError, RefusedError
from cell.features.teach import STORE_NAME, Sample, TaughtPose, TaughtStore, combine
from cell.results.modes import ApproachMode
from cell.service import Cell
from cell.servoing.ibvs import Features
from estimator.transforms import T_from_pose, T_from_pose_dict, invert_T, make_T, pose_distance
from tests.support.cell import AUTH, running_cell, sim_config, tcp, world

OP, PLC, VIEW = AUTH["operator"], AUTH["plc"], AUTH["viewer"]


def _pose(name: str, x: float = 1.0) -> TaughtPose:
    T = T_from_pose([x, 2.0, 3.0], [0.1, 0.2, 0.3])
    return TaughtPose(name, T, 3, 0.01, 0.002, np.eye(4), T, "op(operator)", 1.0)


# -- the store ---------------------------------------------------------------------------------
def test_store_persists_lists_gets_and_deletes(tmp_path: Path) -> None:
    path = tmp_path / STORE_NAME
    store = TaughtStore(path)
    store.put(_pose("b"))
    store.put(_pose("a", 5.0))
    again = TaughtStore(path)  # a restarted service sees the same poses
    assert [p.name for p in again.list()] == ["a", "b"]
    assert np.allclose(again.get("a").T_target_tcp, _pose("a", 5.0).T_target_tcp)
    with pytest.raises(RefusedError):
        again.put(_pose("a"), replace=False)
    again.put(_pose("a", 7.0))  # replace
    assert TaughtStore(path).get("a").T_target_tcp[0, 3] == pytest.approx(7.0)
    again.delete("b")
    assert [p.name for p in TaughtStore(path).list()] == ["a"]
    with pytest.raises(NotFoundError):
        again.get("b")
    with pytest.raises(NotFoundError):
        again.delete("b")
    with pytest.raises(LimitError):
        again.put(_pose("../etc"))
    assert sorted(p.name for p in tmp_path.iterdir()) == [STORE_NAME]  # no temporary files left
    assert json.loads(path.read_text())["version"] == 1


def test_unreadable_store_is_refused_and_never_overwritten(tmp_path: Path) -> None:
    path = tmp_path / STORE_NAME
    path.write_text('{"poses": [{"name": "half')
    store = TaughtStore(path)
    for call in (store.list, lambda: store.get("x"), lambda: store.put(_pose("x"))):
        with pytest.raises(CellError) as err:
            call()
        assert err.value.code == "taught_store_unreadable"
    assert path.read_text() == '{"poses": [{"name": "half'


def test_failed_write_changes_nothing(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    path = tmp_path / STORE_NAME
    store = TaughtStore(path)
    store.put(_pose("a"))
    before = path.read_text()

    def full_disk(src: str, dst: str) -> None:
        raise OSError(28, "No space left on device")

    monkeypatch.setattr("cell.files.os.replace", full_disk)
    with pytest.raises(CellError) as err:
        store.put(_pose("b"))
    assert err.value.code == "taught_store_write_failed"
    with pytest.raises(CellError):
        store.delete("a")
    monkeypatch.undo()
    assert [p.name for p in store.list()] == ["a"]
    assert path.read_text() == before
    assert sorted(p.name for p in tmp_path.iterdir()) == [STORE_NAME]


def test_a_job_takes_its_taught_pose_and_view_from_one_lookup(tmp_path: Path) -> None:
    store = TaughtStore(tmp_path / STORE_NAME)
    view = Features((1, 2, 3, 4), np.zeros((4, 2)), np.full(4, 300.0))
    store.put(replace(_pose("shown"), view=view))
    store.put(_pose("old"))  # taught before views were recorded
    assert store.for_job(None, None) == (None, None)
    assert store.for_job(None, ApproachMode.servo) == (None, None)
    T, no_view = store.for_job("shown", ApproachMode.servo)
    assert np.allclose(T, _pose("shown").T_target_tcp) and no_view is None
    T, shown = store.for_job("shown", ApproachMode.ibvs)
    assert shown is view
    for name, mode, code in ((None, ApproachMode.ibvs, "ibvs_needs_taught"),
                             ("old", ApproachMode.ibvs, "taught_without_view"),
                             ("nope", None, "taught_not_found"),
                             ("", None, "taught_not_found"),
                             (5, None, "taught_not_found")):
        with pytest.raises(CellError) as err:
            store.for_job(name, mode)  # type: ignore[arg-type]
        assert err.value.code == code, (name, mode)


# -- averaging -------------------------------------------------------------------------------
def test_combine_averages_and_reports_the_spread() -> None:
    rng = np.random.default_rng(3)
    T_base_tcp = T_from_pose([-400.0, -100.0, 250.0], [np.pi, 0.0, 0.0])
    T_true = T_from_pose([-480.0, -100.0, 0.0], [np.pi, 0.0, 0.1])
    samples = []
    for k in range(6):
        noise = make_T(Rotation.from_rotvec(rng.normal(0, 1e-4, 3)).as_matrix(),
                       rng.normal(0, 0.05, 3))
        samples.append(Sample(T_true @ noise, T_base_tcp, k))
    taught = combine("pick", samples, "op", 0.5, 0.2)
    d_mm, d_deg = pose_distance(taught.T_target_tcp, invert_T(T_true) @ T_base_tcp)
    assert d_mm < 0.1 and d_deg < 0.02
    assert 0.01 < taught.spread_mm < 0.5 and 0.001 < taught.spread_deg < 0.1
    with pytest.raises(RefusedError) as err:
        combine("pick", samples, "op", 0.001, 0.2)
    assert err.value.code == "spread_too_large"
    moved = [*samples[:-1], Sample(samples[-1].T_base_target,
                                   T_base_tcp @ T_from_pose([0, 0, 0.5], [0, 0, 0]), 9)]
    with pytest.raises(RefusedError) as err:
        combine("pick", moved, "op", 0.5, 0.2)
    assert err.value.code == "arm_moving"


# -- over HTTP on the simulated cell -----------------------------------------------------------
@pytest.fixture
def client(tmp_path: Path) -> Iterator[TestClient]:
    config = sim_config(tmp_path, approach={"speed_mm_s": 250.0, "accel_mm_s2": 1200.0})
    with running_cell(config) as cell, TestClient(create_app(cell)) as c:
        yield c


def cell_of(client: TestClient) -> Cell:
    cell: Cell = client.app.state.cell  # type: ignore[attr-defined]
    return cell


def jog(client: TestClient, translation_mm: list[float],
        rotation_deg: tuple[float, float, float] = (0.0, 0.0, 0.0)) -> None:
    r = client.post("/api/v1/jog", json={"mode": "step", "translation_mm": translation_mm,
                                         "rotation_deg": list(rotation_deg),
                                         "speed_mm_s": 100}, headers=OP)
    assert r.status_code == 200, r.text


def assert_not_moved(cell: Cell, before: np.ndarray) -> None:
    time.sleep(0.2)
    d_mm, d_deg = pose_distance(tcp(cell), before)
    assert d_mm < 0.01 and d_deg < 0.01, f"the arm moved {d_mm:.3f} mm / {d_deg:.3f} deg"


def test_teach_then_approach_by_name_arrives_at_the_taught_pose(
        client: TestClient, tmp_path: Path) -> None:
    cell = cell_of(client)
    # a grasp pose: lower, shifted and turned, the target still in view
    jog(client, [10.0, -20.0, -120.0], (5.0, -3.0, 10.0))
    time.sleep(0.1)
    T_taught = tcp(cell)
    r = client.post("/api/v1/teach", json={"name": "grasp-1", "samples": 5}, headers=OP)
    assert r.status_code == 200, r.text
    taught = r.json()
    assert taught["samples"] == 5
    assert 0 < taught["spread_mm"] < 0.5 and 0 < taught["spread_deg"] < 0.2
    truth = invert_T(world(cell).true_T_base_target()) @ T_taught
    d_mm, d_deg = pose_distance(T_from_pose_dict(taught["T_target_tcp"]), truth)
    print(f"taught T_target_tcp error {d_mm:.3f} mm / {d_deg:.3f} deg, spread "
          f"{taught['spread_mm']:.3f} mm / {taught['spread_deg']:.3f} deg")
    assert d_mm < 0.3 and d_deg < 0.1
    stored = json.loads((tmp_path / STORE_NAME).read_text())["poses"][0]
    assert stored["name"] == "grasp-1"
    # each sample the mean of [teach] frames_per_sample frames; the view says how many it holds
    assert stored["view"]["frames"] == 5 * cell.config.teach.frames_per_sample
    view = cell.taught.get("grasp-1").view
    assert view is not None and view.frames == stored["view"]["frames"]
    listed = client.get("/api/v1/teach", headers=VIEW).json()["taught"]
    assert [p["name"] for p in listed] == ["grasp-1"]
    assert client.get("/api/v1/teach/grasp-1", headers=PLC).json()["T_target_tcp"] == \
        taught["T_target_tcp"]

    jog(client, [30.0, 40.0, 100.0], (0.0, 0.0, -15.0))  # away
    assert pose_distance(tcp(cell), T_taught)[0] > 50
    r = client.post("/api/v1/approach", json={"taught": "grasp-1", "standoff_mm": 0,
                                              "wait": True}, headers=PLC)
    assert r.status_code == 200, r.text
    job = r.json()
    assert job["state"] == "succeeded", job["error"]
    d_mm, d_deg = pose_distance(tcp(cell), T_taught)
    print(f"approach by name: {d_mm:.3f} mm / {d_deg:.3f} deg from the taught pose")
    assert d_mm <= 0.3 and d_deg <= 0.1

    r = client.delete("/api/v1/teach/grasp-1", headers=OP)
    assert r.status_code == 200 and r.json()["deleted"]["name"] == "grasp-1"
    assert client.get("/api/v1/teach/grasp-1", headers=VIEW).status_code == 404
    entries = [e["command"] for e in client.get("/api/v1/audit", headers=VIEW).json()["entries"]]
    assert "teach" in entries and "teach_delete" in entries


def test_refusals_store_nothing_and_move_nothing(client: TestClient) -> None:
    cell = cell_of(client)
    before = tcp(cell)
    r = client.post("/api/v1/approach", json={"taught": "unknown", "wait": True}, headers=PLC)
    assert r.status_code == 404 and r.json()["error"]["code"] == "taught_not_found"
    assert "unknown" in r.json()["error"]["message"]
    assert_not_moved(cell, before)

    for headers in (VIEW, PLC):
        r = client.post("/api/v1/teach", json={"name": "x"}, headers=headers)
        assert r.status_code == 403 and r.json()["error"]["code"] == "forbidden"
    assert client.post("/api/v1/teach", json={"name": "x"}).status_code == 401
    for body in ({"name": "bad name"}, {"name": "x", "samples": 0}, {"samples": 3},
                 {"name": "x", "extra": 1}):
        r = client.post("/api/v1/teach", json=body, headers=OP)
        assert r.status_code == 422 and r.json()["error"]["code"] == "invalid_request", body

    r = client.post("/api/v1/teach", json={"name": "tight", "samples": 4,
                                           "max_spread_mm": 1e-6}, headers=OP)
    assert r.status_code == 409 and r.json()["error"]["code"] == "spread_too_large"
    assert client.get("/api/v1/teach", headers=VIEW).json()["taught"] == []

    r = client.post("/api/v1/teach", json={"name": "p", "samples": 2}, headers=OP)
    assert r.status_code == 200, r.text
    r = client.post("/api/v1/teach", json={"name": "p", "replace": False}, headers=OP)
    assert r.status_code == 409 and r.json()["error"]["code"] == "taught_exists"
    r = client.post("/api/v1/approach", json={"taught": "p", "T_target_tcp": {
        "position_mm": [0, 0, 0], "rotvec_rad": [0, 0, 0]}}, headers=PLC)
    assert r.status_code == 422
    assert client.delete("/api/v1/teach/p", headers=PLC).status_code == 403
    assert client.delete("/api/v1/teach/nope", headers=OP).status_code == 404
    assert_not_moved(cell, before)


def test_cli_teaches_lists_and_deletes_through_the_service(
        client: TestClient, monkeypatch: pytest.MonkeyPatch,
        capsys: pytest.CaptureFixture[str]) -> None:
    from cell.cli import main

    monkeypatch.setattr("cell.commands.teach._client", lambda args: client)

    def run(*argv: str) -> tuple[int, dict[str, Any]]:
        code = main(["teach", "--token", "sim-operator", "--json", *argv])
        return code, json.loads(capsys.readouterr().out)

    code, out = run("add", "cli-pose", "--samples", "3")
    assert code == 0 and out["name"] == "cli-pose" and out["samples"] == 3
    code, out = run("list")
    assert code == 0 and [p["name"] for p in out["taught"]] == ["cli-pose"]
    code, out = run("delete", "cli-pose")
    assert code == 0
    code, out = run("show", "cli-pose")
    assert code == 2 and out["error"]["code"] == "taught_not_found"
    assert main(["teach", "--token", "sim-viewer", "add", "x"]) == 2
    assert "forbidden" in capsys.readouterr().err
    assert main(["teach", "--token", "", "list"]) == 2
    assert "no token" in capsys.readouterr().err
    assert main(["teach", "--token", "sim-viewer", "list"]) == 0
    assert "no taught poses" in capsys.readouterr().out
