"""The Modbus TCP server on the simulated cell, driven by a pymodbus client as a PLC would:
the sequence handshake (approach, stop mid-approach, locate) with the results read back from
the input registers and checked against the simulated truth, a PLC polling every 10 ms,
recipes by number, refused writes from unlisted clients (STOP still accepted), bad commands,
the heartbeat, and the float word order on the wire."""

from __future__ import annotations

import struct
import time
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest
from pymodbus.client import ModbusTcpClient

from api.plc.modbus import (
    ERROR_NUMBERS,
    Alarm,
    Command,
    Ir,
    ModbusServer,
    State,
    float_words,
    words_float,
)
from cell.config.schema import ModbusConfig, load_config
from cell.features.recipes import parse_spec
from cell.service import Cell
from estimator.transforms import pose_distance, pose_from_T
from tests.support.cell import running_cell, settled_tcp, sim_config
from tests.support.modbus import Plc, modbus_client, pose_of
from tests.support.net import free_port

TIMEOUT_S = 60.0


@dataclass
class Served:
    cell: Cell
    server: ModbusServer
    port: int
    stops: list[float]


@pytest.fixture
def served(tmp_path: Path) -> Iterator[Served]:
    port = free_port()
    config = sim_config(tmp_path, approach={"speed_mm_s": 250.0, "accel_mm_s2": 1200.0},
                        modbus={"port": port, "clients": ["127.0.0.1"]})
    stops: list[float] = []
    with running_cell(config) as cell:
        server = ModbusServer(cell, config.modbus, on_stop_sent=stops.append)
        server.start()
        try:
            yield Served(cell, server, port, stops)
        finally:
            server.close()


@pytest.fixture
def plc(served: Served) -> Iterator[Plc]:
    client = ModbusTcpClient("127.0.0.1", port=served.port, timeout=5)
    assert client.connect()
    try:
        yield Plc(client)
    finally:
        client.close()


def test_float_words_are_big_endian_on_the_wire() -> None:
    assert float_words(1.0) == [0x3F80, 0x0000]
    assert words_float(*float_words(-123.25)) == -123.25
    assert struct.pack(">HH", *float_words(40.0)) == struct.pack(">f", 40.0)


def test_approach_then_stop_then_locate_through_the_handshake(served: Served, plc: Plc) -> None:
    cell = served.cell
    assert plc.inputs()[Ir.STATE] == State.IDLE
    # approach: accepted in the write's own request, finished with the located pose
    seq = plc.command(Command.APPROACH, standoff_mm=40.0)
    regs = plc.inputs()
    assert regs[Ir.ACCEPTED_SEQUENCE] == seq and regs[Ir.STATE] == State.BUSY
    assert regs[Ir.FINISHED_SEQUENCE] != seq
    regs = plc.wait(seq)
    assert regs[Ir.STATE] == State.DONE_OK and regs[Ir.ERROR] == 0, regs
    assert cell.sim is not None
    d_mm, d_deg = pose_distance(pose_of(regs), cell.sim.true_T_base_target())
    assert d_mm < 1.0 and d_deg < 0.2, (d_mm, d_deg)
    job = cell.jobs.list_jobs(1)[0]
    assert job.kind == "approach" and job.state == "succeeded" and job.caller.startswith("modbus")
    # a second approach from further back, stopped while it moves
    seq = plc.command(Command.APPROACH, standoff_mm=120.0)
    deadline = time.monotonic() + TIMEOUT_S
    while cell.status().get("state") != "approach" and time.monotonic() < deadline:
        time.sleep(0.01)
    time.sleep(0.3)
    stop_seq = plc.command(Command.STOP)
    regs = plc.wait(stop_seq)
    assert regs[Ir.STATE] == State.DONE_OK and regs[Ir.ERROR] == 0
    assert served.stops, "the stop was not timed"
    deadline = time.monotonic() + TIMEOUT_S
    while cell.jobs.list_jobs(1)[0].state == "running" and time.monotonic() < deadline:
        time.sleep(0.02)
    assert cell.jobs.list_jobs(1)[0].state == "cancelled"
    assert plc.inputs()[Ir.FINISHED_SEQUENCE] == stop_seq  # the overtaken approach stays quiet
    settled_tcp(cell)
    # locate: the pose in the registers is the target's true pose
    seq = plc.command(Command.LOCATE)
    regs = plc.wait(seq, poll_s=0.01)
    assert regs[Ir.STATE] == State.DONE_OK, regs
    d_mm, d_deg = pose_distance(pose_of(regs), cell.sim.true_T_base_target())
    assert d_mm < 1.0 and d_deg < 0.2, (d_mm, d_deg)


def test_a_plc_polling_every_10_ms_never_sees_a_half_finished_command(served: Served,
                                                                     plc: Plc) -> None:
    """Whenever the finished sequence equals the accepted one, state is done or failed and
    the pose is the final one: the end is written in one step."""
    seen: list[list[int]] = []
    for _ in range(3):
        seq = plc.command(Command.LOCATE)
        deadline = time.monotonic() + TIMEOUT_S
        while time.monotonic() < deadline:
            regs = plc.inputs()
            seen.append(regs)
            if regs[Ir.FINISHED_SEQUENCE] == seq:
                break
            assert regs[Ir.ACCEPTED_SEQUENCE] == seq and regs[Ir.STATE] == State.BUSY, regs
            time.sleep(0.01)
        assert regs[Ir.STATE] == State.DONE_OK
        assert served.cell.last_locate is not None
        expected = pose_from_T(served.cell.last_locate.T_base_target)[0]
        got = [words_float(regs[Ir.POSE + 2 * i], regs[Ir.POSE + 2 * i + 1]) for i in range(3)]
        assert np.allclose(got, expected, atol=1e-3)
    assert len(seen) >= 3
    # the heartbeat counts on its own
    h0 = plc.inputs()[Ir.HEARTBEAT]
    time.sleep(0.5)
    assert (plc.inputs()[Ir.HEARTBEAT] - h0) & 0xFFFF >= 2


def test_refusals_have_error_numbers_and_change_nothing(served: Served, plc: Plc) -> None:
    n_jobs = served.cell.jobs.count_jobs()
    seq = plc.command(99)
    regs = plc.wait(seq)
    assert regs[Ir.STATE] == State.FAILED and regs[Ir.ERROR] == ERROR_NUMBERS["unknown_command"]
    assert regs[Ir.ALARMS] & (1 << Alarm.JOB_FAILED)
    seq = plc.command(Command.APPROACH, recipe=77)
    regs = plc.wait(seq)
    assert regs[Ir.STATE] == State.FAILED and regs[Ir.ERROR] == ERROR_NUMBERS["recipe_not_found"]
    seq = plc.command(Command.APPROACH, standoff_mm=float("nan"))
    regs = plc.wait(seq)
    assert regs[Ir.ERROR] == ERROR_NUMBERS["invalid_standoff"]
    assert served.cell.jobs.count_jobs() == n_jobs
    assert not served.cell.commanded()
    # the same sequence again does nothing; reading beyond the map is a Modbus exception
    r = plc.client.write_registers(0, [Command.LOCATE, plc.seq], device_id=1)
    assert not r.isError()
    time.sleep(0.2)
    assert plc.inputs()[Ir.STATE] == State.FAILED
    assert plc.client.read_input_registers(25, count=10, device_id=1).isError()
    assert plc.client.read_input_registers(28, count=2, device_id=1).isError()
    assert not plc.client.read_input_registers(0, count=29, device_id=1).isError()
    assert plc.client.read_holding_registers(0, count=7, device_id=1).isError()


def test_recipe_by_number_is_recorded_in_the_job(served: Served, plc: Plc) -> None:
    cell = served.cell
    t = cell.config.target
    spec = parse_spec({"name": "plate-a", "number": 3, "targets": [{
        "points_mm": [list(p) for p in t.points_mm], "dot_diameter_mm": t.dot_diameter_mm,
        "polarity": t.polarity, "standoff_mm": 60.0}]})
    store = cell.recipes
    store.save(spec, "test")
    saved = store.save(spec, "test")
    assert saved.version == 2
    seq = plc.command(Command.APPROACH, recipe=3)
    regs = plc.wait(seq)
    assert regs[Ir.STATE] == State.DONE_OK, regs
    job = cell.jobs.list_jobs(1)[0]
    assert job.params["recipe"] == {"name": "plate-a", "number": 3, "version": 2,
                                    "target": "main"}
    assert job.params["standoff_mm"] == 60.0


def test_unlisted_clients_may_only_stop(tmp_path: Path) -> None:
    port = free_port()
    config = sim_config(tmp_path, modbus={"port": port, "clients": ["10.9.8.7"]})
    with running_cell(config) as cell, modbus_client(cell, config.modbus) as client:
        plc = Plc(client)
        r = client.write_registers(0, [Command.LOCATE, 1, 0, 0, 0], device_id=1)
        assert r.isError() and r.exception_code == 1
        assert plc.inputs()[Ir.ACCEPTED_SEQUENCE] == 0
        seq = plc.command(Command.STOP)
        assert plc.wait(seq)[Ir.STATE] == State.DONE_OK
        # another unit id gets no answer from this cell
        assert client.read_input_registers(0, count=1, device_id=5).isError()


def test_the_shipped_role_runs_a_production_cycle_home_and_gripper(tmp_path: Path) -> None:
    """With the shipped config (``[modbus] role``, the sim gripper), a PLC homes the arm and
    opens and closes the gripper: the role a PLC runs the cell with covers a cycle."""
    assert load_config().modbus.role == ModbusConfig().role == "plc"
    port = free_port()
    config = sim_config(tmp_path, gripper="sim",
                        approach={"speed_mm_s": 250.0, "accel_mm_s2": 1200.0},
                        modbus={"port": port, "clients": ["127.0.0.1"]})
    assert config.modbus.role == "plc"
    with running_cell(config) as cell:
        with modbus_client(cell, config.modbus) as client:
            plc = Plc(client)
            home_tcp = settled_tcp(cell)
            regs = plc.wait(plc.command(Command.APPROACH, standoff_mm=60.0))
            assert regs[Ir.STATE] == State.DONE_OK, regs
            assert pose_distance(settled_tcp(cell), home_tcp)[0] > 10.0
            regs = plc.wait(plc.command(Command.HOME))
            assert regs[Ir.STATE] == State.DONE_OK and regs[Ir.ERROR] == 0, regs
            assert pose_distance(settled_tcp(cell), home_tcp)[0] < 0.5
            for command in (Command.GRIPPER_OPEN, Command.GRIPPER_CLOSE, Command.GRIPPER_OPEN):
                regs = plc.wait(plc.command(command))
                assert regs[Ir.STATE] == State.DONE_OK and regs[Ir.ERROR] == 0, (command, regs)
        rows = [(e.command, e.outcome) for e in cell.jobs.audit_log(50)
                if e.caller == "modbus:plc(plc)"]
    assert ("home", "ok") in rows and ("gripper", "ok") in rows, rows
