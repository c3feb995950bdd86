"""The calibration check through Modbus TCP, with a pymodbus client as the PLC, on the
simulated cell: command 9 waits for the check and publishes its verdict, its error at the tool
and its cause in input registers 23-28, read back against the job's result; a camera knocked in
the simulator reads verdict 2 (drifted) and sets the drift alarm bit; without a reference the
command fails with its error number and moves nothing; a check from another door shows in the
registers too."""

from __future__ import annotations

import math
import time
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import pytest
from fastapi.testclient import TestClient

from api.app import create_app
from api.plc.modbus import (
    ERROR_NUMBERS,
    Alarm,
    CheckCause,
    CheckVerdict,
    Command,
    Ir,
    State,
    words_float,
)
from cell.results.check import CheckResult
from cell.service import Cell
from tests.support.cell import AUTH, running_cell, sim_config
from tests.support.modbus import Plc, modbus_client
from tests.support.net import free_port
from tests.support.waiting import wait_until

pytestmark = pytest.mark.timeout(240)
CHECK_S = 90.0
KNOCK = {"camera_mount_delta": {"position_mm": [0.35, -0.35, 0.0], "rotvec_rad": [0, 0, 0]}}


@dataclass
class Served:
    cell: Cell
    http: TestClient
    plc: Plc


@pytest.fixture
def served(tmp_path: Path) -> Iterator[Served]:
    config = sim_config(tmp_path, modbus={"port": free_port(), "clients": ["127.0.0.1"]})
    with running_cell(config) as cell, TestClient(create_app(cell)) as http, \
            modbus_client(cell, config.modbus) as client:
        yield Served(cell, http, Plc(client))


def _float(regs: list[int], at: int) -> float:
    return words_float(regs[at], regs[at + 1])


def _newest_check(cell: Cell, caller: str) -> tuple[str, CheckResult]:
    job = cell.jobs.list_jobs(1, kind="calibration_check")[0]
    assert job.state == "succeeded" and job.caller == caller, job.as_dict()
    assert isinstance(job.result, CheckResult)
    return job.id, job.result


def _registers_hold(regs: list[int], result: CheckResult) -> None:
    verdict = CheckVerdict.DRIFTED if result.verdict == "drifted" else CheckVerdict.OK
    cause = CheckCause.CAMERA if result.cause == "camera" else CheckCause.REFERENCE
    assert regs[Ir.CHECK_VERDICT] == verdict and regs[Ir.CHECK_CAUSE] == cause
    # float32 on the wire
    assert _float(regs, Ir.CHECK_TCP_ERROR_MM) == pytest.approx(result.tcp_error_mm, rel=1e-6)
    assert _float(regs, Ir.CHECK_TCP_ERROR_DEG) == pytest.approx(result.tcp_error_deg,
                                                                 rel=1e-6, abs=1e-9)


def _record_reference(served: Served) -> None:
    r = served.http.post("/api/v1/calibration/reference", json={"wait": True},
                         headers=AUTH["operator"])
    assert r.status_code == 200 and r.json()["state"] == "succeeded", r.text


def test_without_a_reference_command_9_fails_and_moves_nothing(served: Served) -> None:
    plc, cell = served.plc, served.cell
    regs = plc.inputs()
    assert regs[Ir.CHECK_VERDICT] == CheckVerdict.NONE
    seq = plc.command(Command.CHECK_CALIBRATION)
    regs = plc.wait(seq)
    assert regs[Ir.STATE] == State.FAILED
    assert regs[Ir.ERROR] == ERROR_NUMBERS["no_reference"] == 31
    assert regs[Ir.CHECK_VERDICT] == CheckVerdict.NONE
    assert math.isnan(_float(regs, Ir.CHECK_TCP_ERROR_MM))
    assert cell.jobs.count_jobs() == 0 and not cell.commanded()
    rows = [(e.caller, e.command, e.outcome) for e in cell.jobs.audit_log(5)]
    assert ("modbus:plc(plc)", "calibration_check", "refused:no_reference") in rows, rows


def test_command_9_ok_then_a_knocked_camera_drifts_and_raises_the_alarm_bit(
        served: Served) -> None:
    plc, cell = served.plc, served.cell
    _record_reference(served)
    seq = plc.command(Command.CHECK_CALIBRATION)
    assert plc.inputs()[Ir.STATE] == State.BUSY  # accepted in the write's own request
    regs = plc.wait(seq, timeout_s=CHECK_S)
    assert regs[Ir.STATE] == State.DONE_OK and regs[Ir.ERROR] == 0
    _, ok = _newest_check(cell, "modbus:plc(plc)")
    assert ok.verdict == "ok" and ok.tcp_error_mm < cell.config.check.tolerance_mm
    _registers_hold(regs, ok)
    assert not regs[Ir.ALARMS] & (1 << Alarm.CALIBRATION_DRIFT)

    r = served.http.put("/api/v1/sim/faults", json=KNOCK, headers=AUTH["operator"])
    assert r.status_code == 200, r.text
    seq = plc.command(Command.CHECK_CALIBRATION)
    regs = plc.wait(seq, timeout_s=CHECK_S)
    # a check that says drifted has done its job: the verdict says the rest
    assert regs[Ir.STATE] == State.DONE_OK and regs[Ir.ERROR] == 0
    _, drifted = _newest_check(cell, "modbus:plc(plc)")
    assert drifted.verdict == "drifted" and drifted.tcp_error_mm > 0.3, drifted
    _registers_hold(regs, drifted)
    assert regs[Ir.CHECK_VERDICT] == CheckVerdict.DRIFTED
    wait_until(lambda: plc.inputs()[Ir.ALARMS] & (1 << Alarm.CALIBRATION_DRIFT),
               timeout_s=10, what="the drift alarm bit")
    alarm = cell.alarms.active_drift()
    assert alarm is not None
    assert served.http.post(f"/api/v1/alarms/{alarm.id}/ack",
                            headers=AUTH["operator"]).status_code == 200
    wait_until(lambda: not plc.inputs()[Ir.ALARMS] & (1 << Alarm.CALIBRATION_DRIFT),
               timeout_s=10, what="the drift alarm bit cleared by the acknowledgement")


def test_a_check_from_another_door_shows_in_the_registers(served: Served) -> None:
    plc, cell = served.plc, served.cell
    _record_reference(served)
    r = served.http.put("/api/v1/sim/faults", json=KNOCK, headers=AUTH["operator"])
    assert r.status_code == 200, r.text
    r = served.http.post("/api/v1/calibration/check", json={"wait": True}, headers=AUTH["plc"])
    assert r.status_code == 200 and r.json()["state"] == "succeeded", r.text
    _, result = _newest_check(cell, "http:plc(plc)")
    assert result.verdict == "drifted"
    wait_until(lambda: plc.inputs()[Ir.CHECK_VERDICT] == CheckVerdict.DRIFTED,
               timeout_s=10, what="the HTTP check in the registers")
    _registers_hold(plc.inputs(), result)
    time.sleep(0.2)
    assert plc.inputs()[Ir.FINISHED_SEQUENCE] == 0  # no command of the PLC's ran
