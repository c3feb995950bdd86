"""The simulated cell the arm benchmarks run on (``cell bench approach`` with its IBVS
section, ``cell bench pick``), the caller they act as in the job and audit records, and
homing between their runs."""

from __future__ import annotations

import time
from pathlib import Path

from cell.config.schema import CellConfig, load_config, parse_config
from cell.errors import CellError
from cell.service import Cell

CALLER = "bench"
HOME_RETRY_S = 30.0
HOME_FAILURES: list[str] = []  # every failed homing of this run, with its reason


def bench_config(state_dir: Path, host: str, lost_after_s: float | None = None,
                 world: str = "ideal") -> CellConfig:
    """The built-in simulated cell on ``host``, its job database in ``state_dir``, in the
    simulated ``world``."""
    data = load_config().model_dump(mode="python")
    data["sim"]["world"] = world
    if lost_after_s is not None:
        data["servo"]["lost_after_s"] = lost_after_s
    data["robot"]["host"] = host
    data["gripper"]["kind"] = "none"
    data["api"]["job_db"] = str(state_dir / "jobs.db")
    data["api"]["calibration_dir"] = ""
    # both modes at the cell's speed and acceleration limits (the servo's caps are those too)
    data["approach"]["speed_mm_s"] = data["limits"]["max_speed_mm_s"]
    data["approach"]["accel_mm_s2"] = data["limits"]["max_accel_mm_s2"]
    return parse_config(data)


def home(cell: Cell) -> None:
    """Home; a failure (e.g. the client stalled past the controller's watchdog on a loaded
    host, and the adapter reconnects) is recorded in HOME_FAILURES and retried for
    ``HOME_RETRY_S`` before the section fails."""
    deadline = time.monotonic() + HOME_RETRY_S
    while True:
        try:
            job = cell.home(CALLER, wait=True)
            if job.state == "succeeded":
                return
            reason = f"{job.error_code}: {job.error_message}"
        except CellError as err:
            reason = f"{err.code}: {err.message}"
        HOME_FAILURES.append(reason)
        if time.monotonic() > deadline:
            raise RuntimeError(f"home failed: {reason}")
        time.sleep(1.0)
