"""The one way a command reaches the audit log: caller, parameters, outcome and times.

Every command, accepted or refused, is a row (``GET /api/v1/audit``); a refusal is written as
``refused:<code>`` with the message the caller got, and counted for ``/metrics``.
"""

from __future__ import annotations

import time
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from typing import Any

from cell.errors import CellError
from cell.jobs.store import JobStore
from cell.stats import CellStats


@dataclass
class AuditNote:
    """What a command adds to its audit row while it runs."""

    detail: str = ""
    job_id: str | None = None
    extra: dict[str, Any] = field(default_factory=dict)


class Auditor:
    def __init__(self, jobs: JobStore, stats: CellStats) -> None:
        self.jobs = jobs
        self.stats = stats

    @contextmanager
    def command(self, caller: str, command: str, params: dict[str, Any]) -> Iterator[AuditNote]:
        """Record the command with its outcome; a CellError is recorded as a refusal."""
        t0 = time.time()
        note = AuditNote()
        try:
            yield note
        except CellError as err:
            self.stats.count_refusal(err.code)
            self.record(caller, command, params, f"refused:{err.code}", err.message,
                        note.job_id, t0)
            raise
        except Exception as err:
            self.record(caller, command, params, "error", repr(err), note.job_id, t0)
            raise
        self.record(caller, command, params, "ok", note.detail, note.job_id, t0)

    def record(self, caller: str, command: str, params: dict[str, Any], outcome: str,
               detail: str = "", job_id: str | None = None,
               started_at: float | None = None) -> None:
        self.jobs.audit(caller, command, params, outcome, detail, job_id, started_at)
