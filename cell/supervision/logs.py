"""Logging set-up for ``cell serve``: plain text for a terminal, one JSON object per line for
journald and log shippers (``--log-format json``).

One ``logging.config.dictConfig`` covers uvicorn's loggers (server and access log) and the
root logger, so the cell's own records (jobs, calibration, device faults) come out in the same
format on stderr. The JSON lines come from python-json-logger.
"""

from __future__ import annotations

import copy
from typing import Any, Literal

LogFormat = Literal["text", "json"]
LOG_FORMATS: tuple[LogFormat, ...] = ("text", "json")

JSON_FIELDS = "%(asctime)s %(levelname)s %(name)s %(message)s"


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
        },
        "root": {"handlers": ["json"], "level": lvl},
    }
