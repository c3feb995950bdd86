"""Job and audit log in SQLite (WAL).

Why SQLite: the log must survive a crash of the service (that is when it is needed most) and be
readable by a person with the ``sqlite3`` tool. WAL lets the API read while a job writes.
A job still marked ``running`` when the store opens was interrupted by a crash or kill; it is
marked ``interrupted`` with a reason and the recovery is written to the audit log.

The store remembers whether its last write failed (:attr:`JobStore.write_error`), so
``/health`` can say the job database cannot be written without touching it;
:meth:`JobStore.probe` makes one tiny write when nothing else wrote for a while.
"""

from __future__ import annotations

import json
import os
import sqlite3
import threading
import time
import uuid
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal

from cell.results.jobs import JobResult, result_from_json, result_json

JobState = Literal["running", "succeeded", "failed", "cancelled", "interrupted"]
FINISHED: tuple[JobState, ...] = ("succeeded", "failed", "cancelled", "interrupted")

_SCHEMA = """
CREATE TABLE IF NOT EXISTS jobs (
    id TEXT PRIMARY KEY,
    kind TEXT NOT NULL,
    caller TEXT NOT NULL,
    params TEXT NOT NULL,
    state TEXT NOT NULL,
    progress TEXT NOT NULL DEFAULT '{}',
    result TEXT,
    error_code TEXT,
    error_message TEXT,
    created_at REAL NOT NULL,
    ended_at REAL,
    pid INTEGER NOT NULL
);
CREATE INDEX IF NOT EXISTS jobs_created ON jobs (created_at);
CREATE INDEX IF NOT EXISTS jobs_kind ON jobs (kind, created_at);
CREATE TABLE IF NOT EXISTS audit (
    id INTEGER PRIMARY KEY AUTOINCREMENT,
    caller TEXT NOT NULL,
    command TEXT NOT NULL,
    params TEXT NOT NULL,
    outcome TEXT NOT NULL,
    detail TEXT NOT NULL DEFAULT '',
    job_id TEXT,
    started_at REAL NOT NULL,
    ended_at REAL NOT NULL
);
CREATE TABLE IF NOT EXISTS write_probe (
    id INTEGER PRIMARY KEY CHECK (id = 1),
    at REAL NOT NULL
);
"""


@dataclass(frozen=True)
class Job:
    """One long-running command (an approach) as stored; times are UNIX seconds. ``result``
    is the model of its kind (:mod:`cell.results.jobs`), set when it succeeded."""

    id: str
    kind: str
    caller: str
    params: dict[str, Any]
    state: JobState
    progress: dict[str, Any]
    result: JobResult | None
    error_code: str | None
    error_message: str | None
    created_at: float
    ended_at: float | None

    @property
    def finished(self) -> bool:
        return self.state in FINISHED

    def error(self) -> dict[str, str] | None:
        """``{code, message}`` of a job that failed, was cancelled or interrupted."""
        if self.error_code is None:
            return None
        return {"code": self.error_code, "message": self.error_message or ""}

    def as_dict(self) -> dict[str, Any]:
        return {
            "id": self.id, "kind": self.kind, "caller": self.caller, "params": self.params,
            "state": self.state, "progress": self.progress,
            "result": None if self.result is None else self.result.json_dict(),
            "error": self.error(),
            "created_at": self.created_at, "ended_at": self.ended_at,
        }


@dataclass(frozen=True)
class AuditEntry:
    id: int
    caller: str
    command: str
    params: dict[str, Any]
    outcome: str
    detail: str
    job_id: str | None
    started_at: float
    ended_at: float

    def as_dict(self) -> dict[str, Any]:
        return dict(self.__dict__)


class JobStore:
    """Thread-safe access to the job and audit tables of one database file."""

    def __init__(self, path: str | Path) -> None:
        self.path = Path(path)
        if str(path) != ":memory:":
            self.path.parent.mkdir(parents=True, exist_ok=True)
        self._lock = threading.Lock()
        self._db = sqlite3.connect(str(path), check_same_thread=False, isolation_level=None)
        self._db.execute("PRAGMA journal_mode=WAL")
        self._db.execute("PRAGMA synchronous=NORMAL")
        self._db.executescript(_SCHEMA)
        # the outcome of the newest write: None after a success, else what failed and when
        self.write_error: str | None = None
        self.write_error_at: float | None = None  # time.time()
        self._last_write_s = time.monotonic()  # of the newest write attempt
        self.recovered: list[str] = self._mark_interrupted()

    def close(self) -> None:
        with self._lock:
            self._db.close()

    @contextmanager
    def _writing(self) -> Iterator[sqlite3.Connection]:
        """The connection, under the lock, for one write; its outcome is remembered."""
        with self._lock:
            self._last_write_s = time.monotonic()
            try:
                yield self._db
            except sqlite3.Error as err:
                if self.write_error is None:
                    self.write_error_at = time.time()
                self.write_error = f"{type(err).__name__}: {err}"
                raise
            self.write_error, self.write_error_at = None, None

    def probe(self, idle_s: float = 0.0) -> str | None:
        """One tiny write (a single row rewritten) unless a write succeeded within the last
        ``idle_s`` seconds; answers :attr:`write_error` afterwards (None: writable)."""
        if self.write_error is None and time.monotonic() - self._last_write_s < idle_s:
            return None
        try:
            with self._writing() as db:
                db.execute("INSERT OR REPLACE INTO write_probe (id, at) VALUES (1, ?)",
                           (time.time(),))
        except sqlite3.Error:
            pass  # remembered by _writing
        return self.write_error

    def _mark_interrupted(self) -> list[str]:
        now = time.time()
        with self._writing():
            rows = self._db.execute(
                "SELECT id, pid FROM jobs WHERE state = 'running'").fetchall()
            for job_id, pid in rows:
                self._db.execute(
                    "UPDATE jobs SET state = 'interrupted', error_code = 'interrupted', "
                    "error_message = ?, ended_at = ? WHERE id = ?",
                    (f"the service (pid {pid}) stopped while this job was running; the arm "
                     "stopped where it was: check the cell before the next job", now, job_id))
                self._db.execute(
                    "INSERT INTO audit (caller, command, params, outcome, detail, job_id, "
                    "started_at, ended_at) VALUES ('service', 'recover', '{}', 'interrupted', "
                    "?, ?, ?, ?)", (f"job left running by pid {pid}", job_id, now, now))
        return [r[0] for r in rows]

    def create(self, kind: str, caller: str, params: dict[str, Any]) -> Job:
        job_id = uuid.uuid4().hex[:12]
        now = time.time()
        with self._writing():
            self._db.execute(
                "INSERT INTO jobs (id, kind, caller, params, state, created_at, pid) "
                "VALUES (?, ?, ?, ?, 'running', ?, ?)",
                (job_id, kind, caller, json.dumps(params), now, os.getpid()))
        job = self.get(job_id)
        assert job is not None
        return job

    def set_progress(self, job_id: str, progress: dict[str, Any]) -> None:
        with self._writing():
            self._db.execute("UPDATE jobs SET progress = ? WHERE id = ?",
                             (json.dumps(progress), job_id))

    def finish(self, job_id: str, state: JobState, result: JobResult | None = None,
               error_code: str | None = None, error_message: str | None = None) -> Job:
        with self._writing():
            self._db.execute(
                "UPDATE jobs SET state = ?, result = ?, error_code = ?, error_message = ?, "
                "ended_at = ? WHERE id = ? AND state = 'running'",
                (state, None if result is None else result_json(result), error_code,
                 error_message, time.time(), job_id))
        job = self.get(job_id)
        assert job is not None
        return job

    def get(self, job_id: str) -> Job | None:
        with self._lock:
            row = self._db.execute(f"{_SELECT_JOBS} WHERE id = ?", (job_id,)).fetchone()
        return None if row is None else _job(row)

    def list_jobs(self, limit: int = 50, offset: int = 0, kind: str | None = None) -> list[Job]:
        """The newest ``limit`` jobs (of ``kind``; None: any) after skipping ``offset``,
        newest first."""
        where, args = ("WHERE kind = ? ", (kind,)) if kind is not None else ("", ())
        with self._lock:
            rows = self._db.execute(
                f"{_SELECT_JOBS} {where}ORDER BY created_at DESC, rowid DESC LIMIT ? OFFSET ?",
                (*args, limit, offset)).fetchall()
        return [_job(r) for r in rows]

    def count_since(self, created_after: float, kinds: tuple[str, ...]) -> int:
        """Jobs of ``kinds`` created after UNIX time ``created_after``."""
        marks = ", ".join("?" * len(kinds))
        with self._lock:
            return int(self._db.execute(
                f"SELECT COUNT(*) FROM jobs WHERE kind IN ({marks}) AND created_at > ?",
                (*kinds, created_after)).fetchone()[0])

    def count_jobs(self) -> int:
        with self._lock:
            return int(self._db.execute("SELECT COUNT(*) FROM jobs").fetchone()[0])

    def audit(self, caller: str, command: str, params: dict[str, Any], outcome: str,
              detail: str = "", job_id: str | None = None, started_at: float | None = None,
              ended_at: float | None = None) -> None:
        end = time.time() if ended_at is None else ended_at
        with self._writing():
            self._db.execute(
                "INSERT INTO audit (caller, command, params, outcome, detail, job_id, "
                "started_at, ended_at) VALUES (?, ?, ?, ?, ?, ?, ?, ?)",
                (caller, command, json.dumps(params, default=str), outcome, detail, job_id,
                 end if started_at is None else started_at, end))

    def audit_log(self, limit: int = 100) -> list[AuditEntry]:
        with self._lock:
            rows = self._db.execute(
                "SELECT id, caller, command, params, outcome, detail, job_id, started_at, "
                "ended_at FROM audit ORDER BY id DESC LIMIT ?", (limit,)).fetchall()
        return [AuditEntry(r[0], r[1], r[2], json.loads(r[3]), r[4], r[5], r[6], r[7], r[8])
                for r in rows]


# The columns in the order _job reads them.
_SELECT_JOBS = ("SELECT id, kind, caller, params, state, progress, result, error_code, "
                "error_message, created_at, ended_at FROM jobs")


def _job(row: tuple[Any, ...]) -> Job:
    return Job(
        id=row[0], kind=row[1], caller=row[2], params=json.loads(row[3]), state=row[4],
        progress=json.loads(row[5]),
        result=None if row[6] is None else result_from_json(row[1], row[6]),
        error_code=row[7], error_message=row[8], created_at=row[9], ended_at=row[10])
