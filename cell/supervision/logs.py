"""Logging set-up for ``cell serve``: plain text for a terminal, one JSON object per line for
journald and log shippers (``--log-format json``).

One ``logging.config.dictConfig`` covers uvicorn's loggers (server and access log) and the
root logger, so the cell's own records (jobs, calibration, device faults) come out in the same
format on stderr. The JSON lines come from python-json-logger.

The PLC libraries' own loggers are kept quiet whatever ``--log-level`` says
(``quiet_library_loggers``): pymodbus and asyncua log at WARNING and above only, and pymodbus'
raw frame dumps (hex bytes it appends to its error lines) never reach a handler. A refusal the
servers expect (a read past the register map, an unknown unit, an anonymous or wrong login) is
logged once by the server in its own words (``api.plc.modbus``, ``api.plc.opcua``), and the
library's line about it is dropped (``drop_library_records``).
"""

from __future__ import annotations

import copy
import logging
from collections.abc import Callable
from typing import Any, Literal

LogFormat = Literal["text", "json"]
LOG_FORMATS: tuple[LogFormat, ...] = ("text", "json")

JSON_FIELDS = "%(asctime)s %(levelname)s %(name)s %(message)s"

# The libraries whose loggers never go below WARNING: pymodbus logs every frame in hex at
# DEBUG, asyncua every request at INFO.
LIBRARY_LOGGERS = ("pymodbus", "asyncua")
LIBRARY_LEVEL = logging.WARNING
FRAME_DUMP_MARK = "\n>>>>> "  # pymodbus appends its last frames to an error line after this


class _LibraryFilter(logging.Filter):
    """On a library's logger: cuts pymodbus' frame dumps off a record and drops the records a
    server has said in its own words (``drops``: predicates on the record)."""

    def __init__(self) -> None:
        super().__init__("")
        self.drops: list[Callable[[logging.LogRecord], bool]] = []

    def filter(self, record: logging.LogRecord) -> bool:
        if record.levelno < LIBRARY_LEVEL:
            return False
        if isinstance(record.msg, str) and FRAME_DUMP_MARK in record.msg:
            record.msg = record.msg.split(FRAME_DUMP_MARK, 1)[0]
        return not any(drop(record) for drop in self.drops)


def _library_filter(name: str) -> _LibraryFilter:
    logger = logging.getLogger(name)
    for f in logger.filters:
        if isinstance(f, _LibraryFilter):
            return f
    f = _LibraryFilter()
    logger.addFilter(f)
    return f


def quiet_library_loggers(*names: str) -> None:
    """pymodbus and asyncua (and ``names``, their modules' loggers, since a logger's filter
    sees only the records made on it) at WARNING, without frame dumps. Idempotent."""
    for name in LIBRARY_LOGGERS:
        logger = logging.getLogger(name)
        if logger.level < LIBRARY_LEVEL:
            logger.setLevel(LIBRARY_LEVEL)
    # pymodbus makes every record on one logger, pymodbus.logging
    for name in ("pymodbus.logging", *names):
        _library_filter(name)


def drop_library_records(name: str, drop: Callable[[logging.LogRecord], bool]) -> None:
    """Records of logger ``name`` for which ``drop`` is true never reach a handler (the
    server logs that event itself). Adding the same function twice adds it once."""
    f = _library_filter(name)
    if drop not in f.drops:
        f.drops.append(drop)


def log_config(fmt: LogFormat, level: str = "info") -> dict[str, Any]:
    """A dictConfig for uvicorn's ``log_config`` and the root logger."""
    from uvicorn.config import LOGGING_CONFIG

    lvl = level.upper()
    if fmt == "text":
        cfg = copy.deepcopy(LOGGING_CONFIG)
        cfg["formatters"]["plain"] = {"format": "%(levelname)s %(name)s: %(message)s"}
        cfg["handlers"]["plain"] = {"class": "logging.StreamHandler", "formatter": "plain",
                                    "stream": "ext://sys.stderr"}
        cfg["root"] = {"handlers": ["plain"], "level": lvl}
        for name in ("uvicorn", "uvicorn.access"):
            cfg["loggers"][name]["level"] = lvl
        cfg["loggers"].update(_library_levels())
        return cfg
    json_formatter = {
        "()": "pythonjsonlogger.json.JsonFormatter",
        "fmt": JSON_FIELDS,
        "rename_fields": {"asctime": "time", "levelname": "level", "name": "logger"},
    }
    handler = {"class": "logging.StreamHandler", "formatter": "json",
               "stream": "ext://sys.stderr"}
    return {
        "version": 1,
        "disable_existing_loggers": False,
        "formatters": {"json": json_formatter},
        "handlers": {"json": handler},
        "loggers": {
            "uvicorn": {"handlers": ["json"], "level": lvl, "propagate": False},
            "uvicorn.error": {"level": lvl},
            "uvicorn.access": {"handlers": ["json"], "level": lvl, "propagate": False},
            **_library_levels(),
        },
        "root": {"handlers": ["json"], "level": lvl},
    }


def _library_levels() -> dict[str, Any]:
    """The libraries' loggers stay at WARNING even under ``--log-level debug``."""
    return {name: {"level": logging.getLevelName(LIBRARY_LEVEL)} for name in LIBRARY_LOGGERS}
