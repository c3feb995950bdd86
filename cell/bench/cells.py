"""The simulated cell the approach benchmarks run on (``cell bench approach`` and its IBVS
section), and the caller they act as in the job and audit records."""

from __future__ import annotations

from pathlib import Path

from cell.config.schema import CellConfig, load_config, parse_config

CALLER = "bench"


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
