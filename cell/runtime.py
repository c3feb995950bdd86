"""Assemble a running Cell from a config: hardware, job store, image log, start."""

from __future__ import annotations

import sys
from collections.abc import Callable
from pathlib import Path

from cell.config.checks import Problem
from cell.config.schema import CellConfig, ConfigError, load_config
from cell.config.tokens import token_problems
from cell.devices.factory import all_simulated, build_hardware, hardware_problems
from cell.jobs.store import JobStore
from cell.service import Cell
from cell.vision.imagelog import ImageLog

# Called first thing on SIGTERM/SIGINT by ``cell serve`` (see cell.commands.serve), before the
# HTTP server waits for open connections: the arm must not wait for an SSE client to leave.
# The app that serves a cell registers its stop here (api.app.app_from_environment).
SHUTDOWN_HOOKS: list[Callable[[], None]] = []


def startup_problems(config: CellConfig) -> list[Problem]:
    """Every reason ``cell serve`` (and any other start path) refuses the loaded ``config``
    before a device is touched: the API token and interface rules on real hardware, and the
    device combinations the factory cannot build. ``cell config check`` fails on the same list,
    so a config that passes the check is one the service starts with."""
    problems = []
    for text in token_problems(config, all_simulated(config)):
        key, _, message = text.partition(": ")
        problems.append(Problem(key, message))
    return problems + hardware_problems(config)


def check_startable(config: CellConfig) -> None:
    """Everything about the config that can refuse a start, before any device is touched
    (ConfigError): a token refusal after the arm was powered on would be too late. The same
    list is what ``cell config check`` fails on."""
    problems = startup_problems(config)
    if problems:
        raise ConfigError("cannot start with this config:\n  "
                          + "\n  ".join(str(p) for p in problems), problems)


# How long a Python thread may hold the GIL while another waits (default 5 ms). The service
# mixes CPU-heavy threads (rendering, estimating, encoding frames) with threads that must
# answer at once (the event loop, the stop thread, the snapshot); each of those takes the GIL
# many times per request, and at 5 ms a turn a STOP or a status read waited tens of ms behind
# one live view.
GIL_SWITCH_INTERVAL_S = 0.001


def start_cell(config: CellConfig | str | Path | None = None,
               config_path: str | Path | None = None) -> Cell:
    """Validate, build and start the cell; on failure everything built so far is released.
    ``config_path``: the file an applied calibration may rewrite (``cell serve``'s config
    file; None: writing the calibration into a config file is refused).

    A device that cannot be reached does not stop the start: the cell serves, reports it
    (``/health``: degraded) and reconnects it in the background."""
    cell = build_cell(config, config_path)
    try:
        cell.start()
    except BaseException:
        cell.close()
        raise
    return cell


STALL_TRACES_FILE = "stall-traces.txt"


def build_cell(config: CellConfig | str | Path | None = None,
               config_path: str | Path | None = None, wait_ready: bool = True,
               stall_traces: bool = False) -> Cell:
    """Validate and build the cell (its hardware, job store and image log), not started: the
    caller runs :meth:`Cell.start`, and :meth:`Cell.close` on any failure after this one.
    ``wait_ready=False`` (``cell serve``): a simulated controller boots while the service
    starts, and the cell's first connect waits for it. ``stall_traces``: write every
    thread's stack to ``stall-traces.txt`` beside the job database when the service stands
    still for seconds (``cell serve``)."""
    cfg = config if isinstance(config, CellConfig) else load_config(config)
    check_startable(cfg)
    sys.setswitchinterval(min(sys.getswitchinterval(), GIL_SWITCH_INTERVAL_S))
    hw = build_hardware(cfg, wait_ready)
    try:
        jobs = JobStore(cfg.api.job_db)
    except BaseException:
        hw.close()
        raise
    image_log = ImageLog(cfg.api.image_log_dir, cfg.api.image_log_max) \
        if cfg.api.image_log_dir else None
    try:
        traces = Path(cfg.api.job_db).parent / STALL_TRACES_FILE if stall_traces else None
        return Cell(cfg, hw, jobs, image_log, config_path, stall_traces=traces)
    except BaseException:
        jobs.close()
        hw.close()
        raise


def freeze_startup_objects() -> None:
    """Move everything alive after start-up (modules, kernels, the cell, the app) out of the
    garbage collector's reach. A full collection walked all of it: 105 ms with every thread
    stopped, measured in the simulated cell's service, so STOP, status and SSE all waited
    whenever one ran (the service benchmark's p99 tails), and 32-74 ms in ``cell bench
    approach``'s process, long enough to starve a servo loop's frame thread into
    ``target_lost``. Collected first, so no garbage is frozen with it; objects made later
    are collected as usual."""
    import gc

    gc.collect()
    gc.freeze()
