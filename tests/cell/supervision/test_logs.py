"""The service's logging set-up keeps the PLC libraries quiet: pymodbus and asyncua stay at
WARNING under ``--log-level debug``, and pymodbus' frame dumps never reach a handler."""

from __future__ import annotations

import logging
import logging.config

import pytest
from pymodbus.logging import Log

from cell.supervision.logs import log_config, quiet_library_loggers


@pytest.mark.parametrize("fmt", ["text", "json"])
def test_library_loggers_stay_at_warning_under_debug(fmt: str) -> None:
    cfg = log_config(fmt, "debug")  # type: ignore[arg-type]
    assert cfg["loggers"]["pymodbus"]["level"] == "WARNING"
    assert cfg["loggers"]["asyncua"]["level"] == "WARNING"


def test_pymodbus_error_lines_lose_their_frame_dumps(caplog: pytest.LogCaptureFixture) -> None:
    quiet_library_loggers()
    caplog.set_level(logging.DEBUG)
    Log.transport_dump(Log.RECV_DATA, b"\x00\x01\x00\x00\x00\x06\x01\x04\x00\x0a\x00\x0a", b"")
    Log.debug("Processing: {}", b"\x00\x01", ":hex")
    Log.error("something the library did not like")
    records = [r for r in caplog.records if r.name.startswith("pymodbus")]
    assert [(r.levelno, r.getMessage()) for r in records] == [
        (logging.ERROR, "something the library did not like")]
