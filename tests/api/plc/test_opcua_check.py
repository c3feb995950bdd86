"""The calibration check through OPC UA, with asyncua as the PLC, on the simulated cell:
``Cell.RecordReference`` is the operator's, ``Cell.CheckCalibration`` answers a job whose
``JobResult`` is the job store's record, and ``Cell/LastCheck`` follows every check that ends
(from this door or another) with its verdict and figures; a camera knocked in the simulator
reads ``drifted``, cause ``camera``."""

from __future__ import annotations

import asyncio
import json
from collections.abc import Iterator
from dataclasses import dataclass
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import pytest
from fastapi.testclient import TestClient

from api.app import create_app
from api.plc.opcua import OpcUaServer
from cell.config.endpoints import opcua_cert_dir
from cell.results.check import CheckResult
from cell.service import Cell
from tests.support.cell import AUTH, running_cell, sim_config
from tests.support.net import free_port
from tests.support.opcua import Opc, opc_client

pytestmark = pytest.mark.timeout(240)
JOB_S = 90.0
KNOCK = {"camera_mount_delta": {"position_mm": [0.35, -0.35, 0.0], "rotvec_rad": [0, 0, 0]}}


@dataclass
class Served:
    cell: Cell
    http: TestClient
    url: str


@pytest.fixture
def served(tmp_path: Path) -> Iterator[Served]:
    port = free_port()
    config = sim_config(tmp_path, opcua={"endpoint": f"opc.tcp://127.0.0.1:{port}"})
    with running_cell(config) as cell, TestClient(create_app(cell)) as http:
        server = OpcUaServer(cell, config.opcua, opcua_cert_dir(config))
        server.start()
        try:
            yield Served(cell, http, f"opc.tcp://127.0.0.1:{port}")
        finally:
            server.close()


async def _last_check(opc: Opc) -> dict[str, Any]:
    folder = await opc.cell.get_child(f"{opc.idx}:LastCheck")
    out = {}
    for name in ("Verdict", "Cause", "TcpErrorMm", "TcpErrorDeg", "Time", "JobId"):
        out[name] = await (await folder.get_child(f"{opc.idx}:{name}")).read_value()
    return out


async def _run(opc: Opc, method: str) -> str:
    """Call a job method, wait for the job's end through the variables; its id."""
    code, message, job_id = await opc.call(method)
    assert code == "ok", message
    assert await opc.read("JobId") == job_id
    await opc.wait_for("JobState", lambda s: s not in ("", "queued", "running"), JOB_S)
    assert await opc.read("JobId") == job_id
    return str(job_id)


def _check_record(cell: Cell, job_id: str, caller: str) -> CheckResult:
    job = cell.job(job_id)
    assert job.kind == "calibration_check" and job.state == "succeeded", job.as_dict()
    assert job.caller == caller
    assert isinstance(job.result, CheckResult)
    return job.result


def _matches(last: dict[str, Any], cell: Cell, job_id: str, result: CheckResult) -> None:
    assert last["JobId"] == job_id
    assert last["Verdict"] == result.verdict and last["Cause"] == result.cause
    assert last["TcpErrorMm"] == pytest.approx(result.tcp_error_mm, abs=1e-12)
    assert last["TcpErrorDeg"] == pytest.approx(result.tcp_error_deg, abs=1e-12)
    ended_at = cell.job(job_id).ended_at
    assert ended_at is not None
    assert last["Time"].replace(tzinfo=UTC).timestamp() == pytest.approx(ended_at, abs=1e-3)


def test_reference_is_the_operators_and_the_check_needs_it(served: Served) -> None:
    cell = served.cell

    async def go() -> None:
        async with Opc(opc_client(served.url, "plc")) as plc:
            code, _, job_id = await plc.call("CheckCalibration")
            assert code == "no_reference" and job_id == ""
            code, _, job_id = await plc.call("RecordReference")
            assert code == "forbidden" and job_id == ""
            last = await _last_check(plc)
            assert last["Verdict"] == "" and last["JobId"] == ""
            assert last["Time"].replace(tzinfo=UTC) == datetime(1601, 1, 1, tzinfo=UTC)
        async with Opc(opc_client(served.url, "viewer")) as viewer:
            code, _, _ = await viewer.call("CheckCalibration")
            assert code == "forbidden"

    asyncio.run(go())
    assert not cell.commanded() and cell.jobs.count_jobs() == 0
    rows = [(e.caller, e.command, e.outcome) for e in cell.jobs.audit_log(20)]
    assert sorted(rows) == [("opcua:plc(plc)", "calibration_check", "refused:no_reference"),
                            ("opcua:plc(plc)", "calibration_reference", "refused:forbidden"),
                            ("opcua:viewer(viewer)", "calibration_check", "refused:forbidden")]


def test_check_through_opcua_ok_then_a_knocked_camera_drifts(served: Served) -> None:
    cell = served.cell

    async def go() -> None:
        async with Opc(opc_client(served.url, "operator")) as operator:
            ref_id = await _run(operator, "RecordReference")
            ref = cell.job(ref_id)
            assert ref.kind == "calibration_reference" and ref.state == "succeeded", \
                ref.as_dict()
            assert ref.caller == "opcua:operator(operator)"
        async with Opc(opc_client(served.url, "plc")) as plc:
            ok_id = await _run(plc, "CheckCalibration")
            ok = _check_record(cell, ok_id, "opcua:plc(plc)")
            assert ok.verdict == "ok" and len(ok.views) == cell.config.check.views
            published = json.loads(await plc.read("JobResult"))
            assert published["job_id"] == ok_id and published["kind"] == "calibration_check"
            assert published["result"] == cell.job(ok_id).result.json_dict()  # type: ignore
            _matches(await _last_check(plc), cell, ok_id, ok)

            r = served.http.put("/api/v1/sim/faults", json=KNOCK, headers=AUTH["operator"])
            assert r.status_code == 200, r.text
            drift_id = await _run(plc, "CheckCalibration")
            drifted = _check_record(cell, drift_id, "opcua:plc(plc)")
            assert drifted.verdict == "drifted", drifted
            assert drifted.tcp_error_mm > cell.config.check.tolerance_mm
            _matches(await _last_check(plc), cell, drift_id, drifted)

            # a check from another door (HTTP) shows in LastCheck too
            assert served.http.delete("/api/v1/sim/faults",
                                      headers=AUTH["operator"]).status_code == 200
            r = served.http.post("/api/v1/calibration/check", json={"wait": True},
                                 headers=AUTH["plc"])
            assert r.status_code == 200 and r.json()["state"] == "succeeded", r.text
            http_id = r.json()["id"]
            for _ in range(100):
                if (await _last_check(plc))["JobId"] == http_id:
                    break
                await asyncio.sleep(0.05)
            http_check = _check_record(cell, http_id, "http:plc(plc)")
            assert http_check.verdict == "ok"
            _matches(await _last_check(plc), cell, http_id, http_check)

    asyncio.run(go())


def test_last_check_survives_a_restart_of_the_door(served: Served, tmp_path: Path) -> None:
    """A new OPC UA server on the same cell shows the newest check from the job store."""
    cell = served.cell
    r = served.http.post("/api/v1/calibration/reference", json={"wait": True},
                         headers=AUTH["operator"])
    assert r.json()["state"] == "succeeded", r.text
    r = served.http.post("/api/v1/calibration/check", json={"wait": True}, headers=AUTH["plc"])
    job_id = r.json()["id"]
    port = free_port()
    config = cell.config.model_copy(update={"opcua": cell.config.opcua.model_copy(
        update={"endpoint": f"opc.tcp://127.0.0.1:{port}"})})
    second = OpcUaServer(cell, config.opcua, opcua_cert_dir(config))
    second.start()
    try:
        async def go() -> None:
            async with Opc(opc_client(f"opc.tcp://127.0.0.1:{port}", "viewer")) as viewer:
                _matches(await _last_check(viewer), cell, job_id,
                         _check_record(cell, job_id, "http:plc(plc)"))

        asyncio.run(go())
    finally:
        second.close()
