"""The pick through Modbus TCP, with a pymodbus client as the PLC, on the simulated cell's parts:
command 7 with the place number in holding register 5, and the part id, parts seen, grip
verdict and finger width read back from input registers 18-22, checked against the job and the
simulator's truth; a part that slips after the last look is a missed grasp (verdict 2, error
26) with the gripper open and the part where it slipped to."""

from __future__ import annotations

import math
import time
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import pytest
from fastapi.testclient import TestClient
from pymodbus.client import ModbusTcpClient

from api.app import create_app
from api.plc.modbus import (
    ERROR_NUMBERS,
    Command,
    GripVerdict,
    Ir,
    ModbusServer,
    State,
    words_float,
)
from cell.results.pick import PickResult
from cell.service import Cell
from estimator.transforms import T_from_pose_dict, pose_dict, pose_distance
from tests.support.cell import AUTH, running_cell, sim_config
from tests.support.modbus import Plc, pose_of
from tests.support.net import free_port
from tests.support.picking import part_at, place_parts, place_pose_for, teach_place, truth_parts

pytestmark = pytest.mark.timeout(240)
PICK_S = 120.0


@dataclass
class Served:
    cell: Cell
    http: TestClient
    plc: Plc


@pytest.fixture
def served(tmp_path: Path) -> Iterator[Served]:
    port = free_port()
    config = sim_config(tmp_path, gripper="sim",
                        approach={"speed_mm_s": 250.0, "accel_mm_s2": 1200.0},
                        modbus={"port": port, "clients": ["127.0.0.1"]})
    with running_cell(config) as cell, TestClient(create_app(cell)) as http:
        server = ModbusServer(cell, config.modbus)
        server.start()
        client = ModbusTcpClient("127.0.0.1", port=port, timeout=5)
        try:
            assert client.connect()
            yield Served(cell, http, Plc(client))
        finally:
            client.close()
            server.close()


def _width_mm(regs: list[int]) -> float:
    return words_float(regs[Ir.GRIP_WIDTH_MM], regs[Ir.GRIP_WIDTH_MM + 1])


def _pick_job(cell: Cell) -> PickResult:
    job = cell.jobs.list_jobs(1)[0]
    assert job.kind == "pick" and job.caller == "modbus:plc(plc)", job.as_dict()
    assert isinstance(job.result, PickResult)
    return job.result


def test_pick_and_place_by_place_number_then_keep_the_next_part(served: Served) -> None:
    cell, plc = served.cell, served.plc
    true_poses = place_parts(served.http, [(0.0, 0.0), (0.0, 140.0)])
    T_goal_part, T_place_tcp = place_pose_for(cell, -200.0, 0.0, 40.0)
    teach_place(cell, "place-2", T_place_tcp)
    before = plc.inputs()
    assert before[Ir.PART_ID] == before[Ir.PARTS_SEEN] == before[Ir.GRIP] == 0

    seq = plc.command(Command.PICK, place=2)
    regs = plc.inputs()
    assert regs[Ir.ACCEPTED_SEQUENCE] == seq and regs[Ir.STATE] == State.BUSY
    regs = plc.wait(seq, timeout_s=PICK_S)
    assert regs[Ir.STATE] == State.DONE_OK and regs[Ir.ERROR] == 0, regs
    result = _pick_job(cell)
    assert result.place is not None and result.place.taught == "place-2"
    assert regs[Ir.PART_ID] == result.part.id > 0
    assert regs[Ir.PARTS_SEEN] == 2
    assert regs[Ir.GRIP] == GripVerdict.HELD
    assert abs(_width_mm(regs) - 40.0) < 0.5
    assert abs(_width_mm(regs) - result.grip.width_mm) < 1e-3  # float32 on the wire
    # the pose registers: the part picked, where it truly lay
    assert min(pose_distance(pose_of(regs), T)[0] for T in true_poses) < 1.0
    # the part lies at its goal (simulator truth), released
    goal = result.place.T_base_part_goal.T()
    assert pose_distance(goal, T_goal_part)[0] < 0.3
    placed = part_at(truth_parts(served.http), goal)
    assert len(placed) == 1 and not placed[0]["held"], placed
    d_mm, d_deg = pose_distance(T_from_pose_dict(placed[0]["T_base_part"]), goal)
    assert d_mm <= 0.3 and d_deg <= 0.1, (d_mm, d_deg)

    # place 0: the next part stays in the gripper
    first_id = regs[Ir.PART_ID]
    regs = plc.wait(plc.command(Command.PICK, place=0), timeout_s=PICK_S)
    assert regs[Ir.STATE] == State.DONE_OK and regs[Ir.ERROR] == 0, regs
    result = _pick_job(cell)
    assert result.place is None and regs[Ir.PART_ID] == result.part.id != first_id
    assert regs[Ir.GRIP] == GripVerdict.HELD and abs(_width_mm(regs) - 40.0) < 0.5
    assert sum(p["held"] for p in truth_parts(served.http)) == 1


def test_a_place_number_never_taught_is_refused_and_moves_nothing(served: Served) -> None:
    cell, plc = served.cell, served.plc
    place_parts(served.http, [(0.0, 0.0)])
    before = truth_parts(served.http)
    regs = plc.wait(plc.command(Command.PICK, place=9))
    assert regs[Ir.STATE] == State.FAILED
    assert regs[Ir.ERROR] == ERROR_NUMBERS["taught_not_found"]
    assert regs[Ir.GRIP] == GripVerdict.NONE and regs[Ir.PART_ID] == 0
    assert not cell.commanded() and truth_parts(served.http) == before


def test_a_part_slipped_after_the_last_look_is_a_missed_grasp(served: Served) -> None:
    """The chosen part moves 8 mm once the pick is in its grasp phase: the fingers close on
    nothing, error 26 (grasp_missed), verdict 2 with the part the pick had chosen, the
    gripper open and no part held. A pick then refused before choosing a part leaves no
    part, count or verdict of the missed one in the registers."""
    cell, plc = served.cell, served.plc
    place_parts(served.http, [(0.0, 0.0), (0.0, 140.0)])
    seq = plc.command(Command.PICK)
    deadline = time.monotonic() + 60
    while True:
        jobs = cell.jobs.list_jobs(1)
        if jobs and jobs[0].progress.get("phase") == "grasp":
            job = jobs[0]
            break
        assert not jobs or jobs[0].state == "running", jobs[0].as_dict()
        assert time.monotonic() < deadline, "the pick never reached its grasp"
        time.sleep(0.005)
    chosen = job.progress["part"]
    parts = truth_parts(served.http)
    seen = T_from_pose_dict(chosen["T_base_target"])
    slipping = min(parts, key=lambda p: pose_distance(T_from_pose_dict(p["T_base_part"]),
                                                      seen)[0])
    T = T_from_pose_dict(slipping["T_base_part"])
    T[:3, 3] += [8.0, 0.0, 0.0]
    r = served.http.put("/api/v1/sim/parts", json={"parts": [
        pose_dict(T) if p["id"] == slipping["id"] else p["T_base_part"] for p in parts]},
        headers=AUTH["operator"])
    assert r.status_code == 200, r.text
    regs = plc.wait(seq, timeout_s=PICK_S)
    assert regs[Ir.STATE] == State.FAILED, regs
    assert regs[Ir.ERROR] == ERROR_NUMBERS["grasp_missed"] == 26
    assert regs[Ir.GRIP] == GripVerdict.MISSED == 2
    assert regs[Ir.PART_ID] == chosen["id"] and regs[Ir.PARTS_SEEN] == 2
    assert math.isnan(_width_mm(regs))  # no grip to measure
    assert cell.job(job.id).error_code == "grasp_missed"
    status = cell.gripper_ops.status()
    assert status is not None and not status["object_detected"] and status["position_mm"] > 80
    after = truth_parts(served.http)
    assert not any(p["held"] for p in after)
    moved = next(p for p in after if p["id"] == slipping["id"])
    assert pose_distance(T_from_pose_dict(moved["T_base_part"]), T)[0] < 1e-6

    # a pick refused before choosing a part clears the last pick's registers
    place_parts(served.http, [(0.0, 1000.0)])  # out of the camera's view
    regs = plc.wait(plc.command(Command.PICK))
    assert regs[Ir.STATE] == State.FAILED, regs
    assert regs[Ir.ERROR] == ERROR_NUMBERS["target_not_visible"] == 6
    assert regs[Ir.PART_ID] == regs[Ir.PARTS_SEEN] == regs[Ir.GRIP] == 0
    assert math.isnan(_width_mm(regs))
