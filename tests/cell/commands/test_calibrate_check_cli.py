"""``cell calibrate reference`` and ``cell calibrate check`` against the simulated cell's
service (its in-process app): the jobs they start are the service's, recorded with the
token's caller; a knocked camera makes ``check`` say drifted and exit 1."""

from __future__ import annotations

import json
from collections.abc import Iterator
from pathlib import Path

import pytest
from fastapi.testclient import TestClient

from api.app import create_app
from cell.cli import main
from tests.support.cell import AUTH, running_cell, sim_config

KNOCK = {"camera_mount_delta": {"position_mm": [0.35, -0.35, 0.0], "rotvec_rad": [0, 0, 0]}}


@pytest.fixture
def client(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Iterator[TestClient]:
    with running_cell(sim_config(tmp_path)) as cell, TestClient(create_app(cell)) as c:
        monkeypatch.setattr("cell.commands.calibration_check._client", lambda args: c)
        yield c


def _run(capsys: pytest.CaptureFixture[str], *argv: str) -> tuple[int, str, str]:
    code = main(["calibrate", *argv])
    out = capsys.readouterr()
    return code, out.out, out.err


def test_reference_then_check_ok_then_drifted(client: TestClient,
                                              capsys: pytest.CaptureFixture[str]) -> None:
    cell = client.app.state.cell  # type: ignore[attr-defined]
    code, _, err = _run(capsys, "check", "--token", "sim-plc")
    assert code == 2 and "no_reference" in err
    code, _, err = _run(capsys, "reference", "--token", "sim-plc")
    assert code == 2 and "forbidden" in err and cell.jobs.count_jobs() == 0
    code, out, _ = _run(capsys, "reference", "--token", "sim-operator")
    assert code == 0 and out.startswith("reference recorded")
    ref = cell.jobs.list_jobs(1, kind="calibration_reference")[0]
    assert ref.state == "succeeded" and ref.caller == "http:operator(operator)"

    code, out, _ = _run(capsys, "check", "--token", "sim-plc", "--json")
    job = json.loads(out)
    assert code == 0 and job["result"]["verdict"] == "ok"
    stored = cell.job(job["id"])
    assert stored.caller == "http:plc(plc)" and stored.result.json_dict() == job["result"]

    assert client.put("/api/v1/sim/faults", json=KNOCK,
                      headers=AUTH["operator"]).status_code == 200
    code, out, _ = _run(capsys, "check", "--token", "sim-plc")
    drifted = cell.jobs.list_jobs(1, kind="calibration_check")[0].result
    assert code == 1 and drifted.verdict == "drifted"
    assert out.startswith("calibration drifted") and f"{drifted.tcp_error_mm:.3f} mm" in out


def test_no_token_is_an_error_without_a_request(capsys: pytest.CaptureFixture[str],
                                                monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.delenv("CELL_TOKEN", raising=False)
    monkeypatch.setattr("cell.commands.calibration_check._client",
                        lambda args: pytest.fail("no request without a token"))
    assert main(["calibrate", "check", "--token", ""]) == 2
    assert "unauthorized" in capsys.readouterr().err
