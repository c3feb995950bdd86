"""Assemble a running Cell from a config: hardware, job store, image log, start."""

from __future__ import annotations

from pathlib import Path

from cell.config import CellConfig, load_config
from cell.factory import build_hardware
from cell.imagelog import ImageLog
from cell.jobs import JobStore
from cell.service import Cell


def start_cell(config: CellConfig | str | Path | None = None) -> Cell:
    """Build and start the cell; on failure everything built so far is released."""
    cfg = config if isinstance(config, CellConfig) else load_config(config)
    hw = build_hardware(cfg)
    try:
        jobs = JobStore(cfg.api.job_db)
    except BaseException:
        hw.close()
        raise
    image_log = ImageLog(cfg.api.image_log_dir, cfg.api.image_log_max) \
        if cfg.api.image_log_dir else None
    cell = Cell(cfg, hw, jobs, image_log)
    try:
        cell.start()
    except BaseException:
        cell.close()
        raise
    return cell
