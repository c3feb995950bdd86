"""The service's logging set-up keeps the PLC libraries quiet: pymodbus and asyncua stay at
WARNING under ``--log-level debug``, and pymodbus' frame dumps never reach a handler."""

from __future__ import annotations

import logging
import logging.config
from collections.abc import Iterator

import pytest
from pymodbus.logging import Log

from cell.supervision.logs import log_config, quiet_library_loggers


@pytest.mark.parametrize("fmt", ["text", "json"])
def test_library_loggers_stay_at_warning_under_debug(fmt: str) -> None:
    cfg = log_config(fmt, "debug")  # type: ignore[arg-type]
    assert cfg["loggers"]["pymodbus"]["level"] == "WARNING"
    assert cfg["loggers"]["asyncua"]["level"] == "WARNING"


class _Records(logging.Handler):
    def __init__(self) -> None:
        super().__init__(logging.DEBUG)
        self.records: list[logging.LogRecord] = []

    def emit(self, record: logging.LogRecord) -> None:
        self.records.append(record)


@pytest.fixture
def pymodbus_records() -> Iterator[list[logging.LogRecord]]:
    """What reaches a handler on pymodbus' logger, with the loggers as a new process has them
    (other tests in this process may have changed levels or pymodbus' repeat memory)."""
    loggers = [logging.getLogger(n) for n in ("pymodbus", "pymodbus.logging")]
    saved = [(lg.level, lg.disabled, lg.propagate) for lg in loggers]
    for lg in loggers:
        lg.setLevel(logging.NOTSET)
        lg.disabled = False
    Log.last_log_text = ""
    Log.frame_dump = []
    handler = _Records()
    loggers[0].addHandler(handler)
    yield handler.records
    loggers[0].removeHandler(handler)
    for lg, (level, disabled, propagate) in zip(loggers, saved, strict=True):
        lg.setLevel(level)
        lg.disabled, lg.propagate = disabled, propagate


def test_pymodbus_error_lines_lose_their_frame_dumps(
        pymodbus_records: list[logging.LogRecord]) -> None:
    quiet_library_loggers()
    Log.transport_dump(Log.RECV_DATA, b"\x00\x01\x00\x00\x00\x06\x01\x04\x00\x0a\x00\x0a", b"")
    Log.debug("Processing: {}", b"\x00\x01", ":hex")
    Log.error("something the library did not like")
    assert [(r.levelno, r.getMessage()) for r in pymodbus_records] == [
        (logging.ERROR, "something the library did not like")]
