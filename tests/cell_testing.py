"""Helpers for the cell and API tests: a fast simulated cell (in-process arm) per test."""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from cell.config import CellConfig, load_config, parse_config
from cell.runtime import start_cell
from cell.service import Cell

AUTH = {role: {"Authorization": f"Bearer sim-{role}"} for role in ("viewer", "operator", "plc")}


def sim_config(tmp_path: Path, *, robot: str = "sim", host: str = "127.0.0.1",
               gripper: str = "none", **tables: dict[str, Any]) -> CellConfig:
    """The built-in sim config with the in-process arm (or the controller at ``host``), a job
    database under ``tmp_path`` and any table values overridden."""
    data = load_config().model_dump(mode="python")
    data["robot"].update(kind=robot, host=host)
    data["sim"]["ur_controller"] = robot == "ur"
    data["gripper"]["kind"] = gripper
    data["api"]["job_db"] = str(tmp_path / "jobs.db")
    for name, values in tables.items():
        data[name].update(values)
    return parse_config(data)


@contextmanager
def running_cell(config: CellConfig) -> Iterator[Cell]:
    cell = start_cell(config)
    try:
        yield cell
    finally:
        cell.close()


def tcp(cell: Cell) -> NDArray[np.float64]:
    """The true TCP pose of the simulated arm."""
    T: NDArray[np.float64] = cell.sim.true_T_base_tcp()
    return T
