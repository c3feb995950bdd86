"""Tokens never reach a log line: ``?token=`` values are redacted from every record that
passes the service's loggers and handlers, uvicorn's access log included.

Why a filter and not "do not log URLs": the access log is what an integrator reads first, and
the streaming routes (frames, events) must accept a token in the URL for ``<img>`` and
``EventSource``. The filter edits the record's arguments in place, so formatters that read
them (uvicorn's access formatter reads ``args`` directly) print the redacted text.
"""

from __future__ import annotations

import logging
import re
from typing import Any

_TOKEN = re.compile(r"((?:\?|&|%3F|%26)token=)[^&\s\"']*", re.IGNORECASE)
_BEARER = re.compile(r"(Bearer\s+)[^\s\"',]+", re.IGNORECASE)
REDACTED = "[redacted]"
LOGGERS = ("", "uvicorn", "uvicorn.access", "uvicorn.error", "fastapi")


def redact(text: str) -> str:
    return _BEARER.sub(rf"\1{REDACTED}", _TOKEN.sub(rf"\1{REDACTED}", text))


def _clean(value: Any) -> Any:
    return redact(value) if isinstance(value, str) else value


class RedactTokens(logging.Filter):
    def filter(self, record: logging.LogRecord) -> bool:
        if isinstance(record.msg, str):
            record.msg = redact(record.msg)
        if isinstance(record.args, tuple):
            record.args = tuple(_clean(a) for a in record.args)
        elif isinstance(record.args, dict):
            record.args = {k: _clean(v) for k, v in record.args.items()}
        return True


_FILTER = RedactTokens()


def install() -> None:
    """Attach the filter to the service's loggers and to every handler they have now (a
    logger's filter does not see records propagated from its children; a handler's does)."""
    for name in LOGGERS:
        logger = logging.getLogger(name)
        if _FILTER not in logger.filters:
            logger.addFilter(_FILTER)
        for handler in logger.handlers:
            if _FILTER not in handler.filters:
                handler.addFilter(_FILTER)
