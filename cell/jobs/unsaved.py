"""What the job store could not write, kept in memory until it can.

Why: a full or failing disk must not strand a job. Its end is what a caller waiting on HTTP, a
PLC polling OPC UA or Modbus and the event stream all wait for; the store answers every read
from here first, so the end reaches them from memory, and writes it when the disk works again.
Audit rows are kept up to ``MAX_AUDIT_ROWS`` (the oldest are dropped beyond, and counted): a
refusal loop against a dead disk must not grow memory without bound.
"""

from __future__ import annotations

import threading
from collections import deque
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from cell.jobs.store import Job

# caller, command, params (JSON), outcome, detail, job_id, started_at, ended_at
AuditRow = tuple[str, str, str, str, str, Any, float, float]
MAX_AUDIT_ROWS = 10_000


class Unsaved:
    """Job rows (ended, or running with newer progress) and audit rows not yet written."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._jobs: dict[str, Job] = {}
        self._audit: deque[AuditRow] = deque(maxlen=MAX_AUDIT_ROWS)
        self.dropped_audit = 0

    @property
    def count(self) -> int:
        return len(self._jobs) + len(self._audit)

    def job(self, job_id: str) -> Job | None:
        return self._jobs.get(job_id)

    def keep_end(self, job: Job) -> None:
        with self._lock:
            self._jobs[job.id] = job

    def keep_running(self, job: Job) -> None:
        """A running job's newer progress; an end kept already wins."""
        with self._lock:
            kept = self._jobs.get(job.id)
            if kept is None or not kept.finished:
                self._jobs[job.id] = job

    def forget(self, job_id: str) -> None:
        with self._lock:
            self._jobs.pop(job_id, None)

    def keep_audit(self, row: AuditRow) -> None:
        with self._lock:
            if len(self._audit) == self._audit.maxlen:
                self.dropped_audit += 1
            self._audit.append(row)

    def audit_rows(self) -> list[AuditRow]:
        with self._lock:
            return list(self._audit)

    def ended_since(self, after_s: float) -> list[Job]:
        with self._lock:
            return [j for j in self._jobs.values()
                    if j.ended_at is not None and j.ended_at >= after_s]

    def snapshot(self) -> tuple[list[Job], list[AuditRow]]:
        with self._lock:
            return list(self._jobs.values()), list(self._audit)

    def written(self, jobs: list[Job], rows: list[AuditRow]) -> None:
        """Forget what :meth:`snapshot` handed out and has been written; what came meanwhile
        stays."""
        with self._lock:
            for job in jobs:
                if self._jobs.get(job.id) is job:
                    del self._jobs[job.id]
            for _ in range(min(len(rows), len(self._audit))):
                self._audit.popleft()
