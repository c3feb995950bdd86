"""Helpers for the cell and API tests: a fast simulated cell (in-process arm) per test."""

from __future__ import annotations

import re
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from cell.config.schema import CellConfig, load_config, parse_config
from cell.devices.hardware import SimWorld
from cell.runtime import start_cell
from cell.service import Cell

AUTH = {role: {"Authorization": f"Bearer sim-{role}"} for role in ("viewer", "operator", "plc")}


def sim_config(tmp_path: Path, *, robot: str = "sim", host: str = "127.0.0.1",
               gripper: str = "none", **tables: dict[str, Any]) -> CellConfig:
    """The built-in sim config with the in-process arm (or the controller at ``host``), a job
    database under ``tmp_path`` and any table values overridden. Approaches default to
    look-and-move here (the tests written for it); servo tests ask for ``mode="servo"``.

    A streamed loop here fails ``target_lost`` only after 5 s without any frame examined (the
    product's default is 1 s): a loaded 2-core test host can hold the estimator that long, and
    that stall is the host's, not the behaviour under test (the stall rule has its own tests)."""
    data = load_config().model_dump(mode="python")
    data["approach"]["mode"] = "look_and_move"
    data["robot"].update(kind=robot, host=host)
    data["sim"]["ur_controller"] = robot == "ur"
    data["gripper"]["kind"] = gripper
    data["api"]["job_db"] = str(tmp_path / "jobs.db")
    data["api"]["calibration_dir"] = str(tmp_path / "calibration")
    data["modbus"]["port"] = 0  # sim.toml's fixed 1502 would be fought over; tests pick one
    data["servo"]["stall_after_s"] = 5.0
    for name, values in tables.items():
        data[name].update(values)
    return parse_config(data)


@contextmanager
def running_cell(config: CellConfig, config_path: Path | None = None) -> Iterator[Cell]:
    """A started cell, closed after the block; ``config_path``: the file an applied
    calibration may write (as ``cell serve``'s config file)."""
    cell = start_cell(config, config_path)
    try:
        yield cell
    finally:
        cell.close()


def tcp(cell: Cell) -> NDArray[np.float64]:
    """The true TCP pose of the simulated arm."""
    assert cell.sim is not None
    return cell.sim.true_T_base_tcp()


def world(cell: Cell) -> SimWorld:
    """The simulated world of a cell built on fakes."""
    assert cell.sim is not None, "the cell does not run on fakes"
    return cell.sim


def settled_tcp(cell: Cell, timeout_s: float = 5.0) -> NDArray[np.float64]:
    """The true TCP pose once the arm has come to rest (two reads 0.1 s apart agree)."""
    deadline = time.monotonic() + timeout_s
    prev = tcp(cell)
    while True:
        time.sleep(0.1)
        now = tcp(cell)
        if np.abs(now - prev).max() < 1e-4 or time.monotonic() > deadline:
            return now
        prev = now


def without_interfaces(text: str) -> str:
    """sim.toml's text with its OPC UA server, XML-RPC endpoint and Modbus server off: their
    ports are the fixed 4840, 8001 and 1502, which parallel test runs (and a running ``make
    run``) would fight over. Tests of those interfaces give ``cell serve --opcua-port N
    --xmlrpc-port N --modbus-port N`` free ones."""
    text, n_opcua = re.subn(r"(\[opcua\][^\[]*?)^enabled = true$", r"\1enabled = false", text,
                            flags=re.M | re.S)
    text, n_rpc = re.subn(r"^xmlrpc_port = \d+$", "xmlrpc_port = 0", text, flags=re.M)
    text, n_modbus = re.subn(r"(\[modbus\][^\[]*?)^port = \d+$", r"\1port = 0", text,
                             flags=re.M | re.S)
    assert n_opcua == 1 and n_rpc == 1 and n_modbus == 1, \
        "sim.toml no longer has [opcua] enabled / xmlrpc_port / [modbus] port"
    return text


def mount_off(tmp_path: Path) -> dict[str, object]:
    """``[sim]`` values that put the camera's true mount off the hand-eye calibration by
    the loops bench's error (the simulator's truth, which the cell does not share)."""
    from cell.bench.loops import MOUNT_ERROR_AXIS, MOUNT_ERROR_DEG, MOUNT_ERROR_MM

    config = sim_config(tmp_path)
    he = config.hand_eye.T_flange_camera
    axis = np.asarray(MOUNT_ERROR_AXIS) / np.linalg.norm(MOUNT_ERROR_AXIS)
    return {"T_flange_camera": {
        "position_mm": (np.asarray(he.position_mm) + MOUNT_ERROR_MM).tolist(),
        "rotvec_rad": (axis * np.radians(MOUNT_ERROR_DEG)).tolist()}}


def standing_tcp(cell: Cell, still_mm: float, timeout_s: float = 3.0) -> NDArray[np.float64]:
    """The true TCP once two reads 0.1 s apart are within ``still_mm`` (AssertionError if the
    arm never stands within ``timeout_s``: what a STOP race checks after the answer)."""
    from estimator.transforms import pose_distance

    prev = tcp(cell)
    deadline = time.monotonic() + timeout_s
    while True:
        time.sleep(0.1)
        now = tcp(cell)
        if pose_distance(prev, now)[0] < still_mm:
            return now
        assert time.monotonic() < deadline, "the arm still moves after the stop answered"
        prev = now
