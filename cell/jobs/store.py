"""Job and audit log in SQLite (WAL).

Why SQLite: the log must survive a crash of the service (that is when it is needed most) and be
readable by a person with the ``sqlite3`` tool. WAL lets the API read while a job writes.
A job still marked ``running`` when the store opens was interrupted by a crash or kill; it is
marked ``interrupted`` with a reason and the recovery is written to the audit log.

The store remembers whether its last write failed (:attr:`JobStore.write_error`), so
``/health`` can say the job database cannot be written without touching it;
:meth:`JobStore.probe` makes one tiny write when nothing else wrote for a while.

A write that fails (a full disk, an I/O error) never strands a job: the end of a job and the
audit rows that could not be written are kept in memory (:mod:`cell.jobs.unsaved`) and every
read answers from them, so each interface sees the job end; they are written as soon as a
write succeeds again. A new job is refused (``storage_failed``) while its row cannot be
created, and the listeners of :meth:`JobStore.on_write_failed` hear of the first failure (the
cell stops a running job: nothing it does could be recorded).

New databases use incremental auto-vacuum, so the pages the retention frees
(:mod:`cell.supervision.retention`) can be handed back to the file system in small steps.
"""

from __future__ import annotations

import json
import logging
import os
import sqlite3
import threading
import time
import uuid
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any, Literal

from cell.error_codes import ErrorCode
from cell.errors import UnavailableError
from cell.jobs.unsaved import AuditRow, Unsaved
from cell.results.jobs import JobResult, result_from_json, result_json

log = logging.getLogger(__name__)

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
CREATE INDEX IF NOT EXISTS jobs_ended ON jobs (ended_at);
CREATE INDEX IF NOT EXISTS jobs_running ON jobs (state) WHERE state = 'running';
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
        # the outcome of the newest write: None after a success, else what failed and when
        self.write_error: str | None = None
        self.write_error_at: float | None = None  # time.time()
        self._last_write_s = time.monotonic()  # of the newest write attempt
        self._unsaved = Unsaved()
        self._failure_listeners: list[Callable[[str], None]] = []
        self._db = sqlite3.connect(str(path), check_same_thread=False, isolation_level=None)
        self._open()
        self.recovered: list[str] = self._mark_interrupted()

    def _open(self) -> None:
        """Settings and tables. On a file that cannot be written (a full disk) an existing
        database is used as it is, degraded (:attr:`write_error` says why); only a database
        without its tables refuses to open."""
        try:
            with self._writing() as db:
                # takes effect only while the file is empty: new databases vacuum incrementally
                db.execute("PRAGMA auto_vacuum = INCREMENTAL")
                db.execute("PRAGMA journal_mode=WAL")
                db.execute("PRAGMA synchronous=NORMAL")
                db.executescript(_SCHEMA)
        except sqlite3.Error as err:
            tables = {r[0] for r in self._db.execute(
                "SELECT name FROM sqlite_master WHERE type = 'table'")}
            if not {"jobs", "audit"} <= tables:
                raise
            log.error("the job database %s cannot be written (%s): serving degraded",
                      self.path, err)

    def close(self) -> None:
        with self._lock:
            self._db.close()

    def on_write_failed(self, listener: Callable[[str], None]) -> None:
        """Call ``listener(error)`` when a write fails after writes worked (once per outage,
        outside the store's lock)."""
        self._failure_listeners.append(listener)

    @property
    def unsaved(self) -> int:
        """How many job ends and audit rows wait in memory for the database."""
        return self._unsaved.count

    @contextmanager
    def _writing(self) -> Iterator[sqlite3.Connection]:
        """The connection, under the lock, for one write; its outcome is remembered, and
        what waits in memory is written after the first write that works again."""
        failed_now: str | None = None
        try:
            with self._lock:
                self._last_write_s = time.monotonic()
                try:
                    yield self._db
                except sqlite3.Error as err:
                    if self.write_error is None:
                        self.write_error_at = time.time()
                        failed_now = f"{type(err).__name__}: {err}"
                    self.write_error = f"{type(err).__name__}: {err}"
                    raise
                if self._unsaved.count:
                    self._flush_locked()
                if self._unsaved.count == 0:
                    self.write_error, self.write_error_at = None, None
        finally:
            if failed_now is not None:
                log.error("the job database %s cannot be written: %s", self.path, failed_now)
                for listener in self._failure_listeners:
                    try:
                        listener(failed_now)
                    except Exception:
                        log.exception("a listener of the store's write failure failed")

    def _flush_locked(self) -> None:
        """Write what waits in memory, in one transaction (kept when it fails)."""
        jobs, rows = self._unsaved.snapshot()
        try:
            self._db.execute("BEGIN IMMEDIATE")
            for job in jobs:
                self._db.execute(
                    "UPDATE jobs SET state = ?, progress = ?, result = ?, error_code = ?, "
                    "error_message = ?, ended_at = ? WHERE id = ? AND state = 'running'",
                    (job.state, json.dumps(job.progress),
                     None if job.result is None else result_json(job.result), job.error_code,
                     job.error_message, job.ended_at, job.id))
            self._db.executemany(_INSERT_AUDIT, rows)
            self._db.execute("COMMIT")
        except sqlite3.Error as err:
            if self._db.in_transaction:
                self._db.execute("ROLLBACK")
            self.write_error = f"{type(err).__name__}: {err}"
            return
        self._unsaved.written(jobs, rows)
        log.warning("the job database is writable again: %d job ends and %d audit rows kept "
                    "in memory are written (%d audit rows were dropped meanwhile)",
                    len(jobs), len(rows), self._unsaved.dropped_audit)

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
        with self._lock:
            rows = self._db.execute(
                f"{_SELECT_JOBS} WHERE state = 'running'").fetchall()
            pids = dict(self._db.execute("SELECT id, pid FROM jobs WHERE state = 'running'"))
        for row in rows:
            job, pid = _job(row), pids.get(row[0])
            message = (f"the service (pid {pid}) stopped while this job was running; the arm "
                       "stopped where it was: check the cell before the next job")
            self._end(replace(job, state="interrupted", error_code="interrupted",
                              error_message=message, ended_at=now))
            self.audit("service", "recover", {}, "interrupted",
                       f"job left running by pid {pid}", job.id, now, now)
        return [r[0] for r in rows]

    def create(self, kind: str, caller: str, params: dict[str, Any]) -> Job:
        """The new job's row (UnavailableError ``storage_failed`` when it cannot be written:
        a job that cannot be recorded does not start)."""
        job_id = uuid.uuid4().hex[:12]
        now = time.time()
        try:
            with self._writing():
                self._db.execute(
                    "INSERT INTO jobs (id, kind, caller, params, state, created_at, pid) "
                    "VALUES (?, ?, ?, ?, 'running', ?, ?)",
                    (job_id, kind, caller, json.dumps(params), now, os.getpid()))
        except sqlite3.Error as err:
            raise UnavailableError(
                ErrorCode.storage_failed, f"the job database cannot be written ({err}): no "
                "job starts until it can; STOP and status still work") from err
        job = self.get(job_id)
        assert job is not None
        return job

    def set_progress(self, job_id: str, progress: dict[str, Any]) -> None:
        """The job's progress; kept in memory when it cannot be written (the store's
        failure listeners hear of that)."""
        try:
            with self._writing():
                self._db.execute("UPDATE jobs SET progress = ? WHERE id = ?",
                                 (json.dumps(progress), job_id))
        except sqlite3.Error:
            job = self.get(job_id)
            if job is not None and not job.finished:
                self._unsaved.keep_running(replace(job, progress=progress))

    def finish(self, job_id: str, state: JobState, result: JobResult | None = None,
               error_code: str | None = None, error_message: str | None = None) -> Job:
        """The job as it ended; never raises for the database: an end that cannot be
        written is kept in memory, read back by every reader, and written later."""
        job = self.get(job_id)
        assert job is not None
        if job.finished:
            return job
        return self._end(replace(job, state=state, result=result, error_code=error_code,
                                 error_message=error_message, ended_at=time.time()))

    def _end(self, job: Job) -> Job:
        try:
            with self._writing():
                self._db.execute(
                    "UPDATE jobs SET state = ?, result = ?, error_code = ?, error_message = ?, "
                    "ended_at = ? WHERE id = ? AND state = 'running'",
                    (job.state, None if job.result is None else result_json(job.result),
                     job.error_code, job.error_message, job.ended_at, job.id))
        except sqlite3.Error:
            self._unsaved.keep_end(job)
            return job
        self._unsaved.forget(job.id)
        ended = self.get(job.id)
        assert ended is not None
        return ended

    def get(self, job_id: str) -> Job | None:
        kept = self._unsaved.job(job_id)
        if kept is not None:
            return kept
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
        return [self._unsaved.job(r[0]) or _job(r) for r in rows]

    def ended_since(self, after_s: float) -> list[Job]:
        """Jobs that ended at or after UNIX time ``after_s``, oldest end first (an index
        range: the alarm watch asks twice a second)."""
        with self._lock:
            rows = self._db.execute(f"{_SELECT_JOBS} WHERE ended_at >= ? ORDER BY ended_at",
                                    (after_s,)).fetchall()
        jobs = [_job(r) for r in rows] + self._unsaved.ended_since(after_s)
        return sorted(jobs, key=lambda j: j.ended_at or 0.0)

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
        """One audit row; kept in memory (bounded) when it cannot be written."""
        end = time.time() if ended_at is None else ended_at
        row: AuditRow = (caller, command, json.dumps(params, default=str), outcome, detail,
                         job_id, end if started_at is None else started_at, end)
        try:
            with self._writing():
                self._db.execute(_INSERT_AUDIT, row)
        except sqlite3.Error:
            self._unsaved.keep_audit(row)

    def audit_log(self, limit: int = 100) -> list[AuditEntry]:
        """The newest ``limit`` rows, newest first; rows waiting in memory first (id 0)."""
        kept = [AuditEntry(0, r[0], r[1], json.loads(r[2]), r[3], r[4], r[5], r[6], r[7])
                for r in self._unsaved.audit_rows()[::-1][:limit]]
        with self._lock:
            rows = self._db.execute(
                "SELECT id, caller, command, params, outcome, detail, job_id, started_at, "
                "ended_at FROM audit ORDER BY id DESC LIMIT ?", (limit - len(kept),)).fetchall()
        return kept + [AuditEntry(r[0], r[1], r[2], json.loads(r[3]), r[4], r[5], r[6], r[7],
                                  r[8]) for r in rows]


_INSERT_AUDIT = ("INSERT INTO audit (caller, command, params, outcome, detail, job_id, "
                 "started_at, ended_at) VALUES (?, ?, ?, ?, ?, ?, ?, ?)")
class Pruning:
    """The retention's deletes on one store, each a bounded batch through an index."""

    def __init__(self, store: JobStore) -> None:
        self.store = store

    def jobs(self, created_before_s: float, limit: int, keep_kinds: tuple[str, ...] = ()
             ) -> int:
        """Delete up to ``limit`` ended jobs created before ``created_before_s``, oldest
        first, except those of ``keep_kinds``; how many went."""
        marks = ", ".join("?" * len(keep_kinds))
        keep = f"AND kind NOT IN ({marks}) " if keep_kinds else ""
        return self._delete(
            "DELETE FROM jobs WHERE rowid IN (SELECT rowid FROM jobs WHERE created_at < ? "
            f"AND state != 'running' {keep}ORDER BY created_at LIMIT ?)",
            (created_before_s, *keep_kinds, limit))

    def audit(self, ended_before_s: float, limit: int) -> int:
        """Delete those of the oldest ``limit`` audit rows that ended before
        ``ended_before_s`` (rows are written in time order: the oldest ids are the oldest
        rows, and the batch never scans beyond them)."""
        return self._delete(
            "DELETE FROM audit WHERE id IN (SELECT id FROM audit ORDER BY id LIMIT ?) "
            "AND ended_at < ?", (limit, ended_before_s))

    def used_bytes(self) -> int:
        """The pages in use (the file less its free pages)."""
        db, lock = self.store._db, self.store._lock
        with lock:
            pages = db.execute("PRAGMA page_count").fetchone()[0]
            free = db.execute("PRAGMA freelist_count").fetchone()[0]
            size = db.execute("PRAGMA page_size").fetchone()[0]
        return int((pages - free) * size)

    def incremental(self) -> bool:
        with self.store._lock:
            return int(self.store._db.execute("PRAGMA auto_vacuum").fetchone()[0]) == 2

    def release(self, pages: int) -> int:
        """Hand up to ``pages`` free pages back to the file system (incremental vacuum);
        how many it handed back."""
        with self.store._writing() as db:
            before = int(db.execute("PRAGMA freelist_count").fetchone()[0])
            # a script runs the pragma to its end (each step of it frees one page)
            db.executescript(f"PRAGMA incremental_vacuum({int(pages)});")
            return before - int(db.execute("PRAGMA freelist_count").fetchone()[0])

    def checkpoint(self) -> None:
        """Copy the WAL into the file and empty it: the file takes its shrunken size, and
        the WAL its smallest (a reader in the way leaves it for the next pass)."""
        with self.store._writing() as db:
            db.execute("PRAGMA wal_checkpoint(TRUNCATE)").fetchall()

    def make_incremental(self) -> None:
        """Rewrite a database made without incremental auto-vacuum (one VACUUM: writes wait
        meanwhile; the retention does this only while the cell is idle and the file small)."""
        with self.store._writing() as db:
            db.execute("PRAGMA auto_vacuum = INCREMENTAL")
            db.execute("VACUUM")

    def _delete(self, sql: str, args: tuple[Any, ...]) -> int:
        with self.store._writing() as db:
            return max(0, db.execute(sql, args).rowcount)


# The columns in the order _job reads them.
_SELECT_JOBS = ("SELECT id, kind, caller, params, state, progress, result, error_code, "
                "error_message, created_at, ended_at FROM jobs")


def _job(row: tuple[Any, ...]) -> Job:
    return Job(
        id=row[0], kind=row[1], caller=row[2], params=json.loads(row[3]), state=row[4],
        progress=json.loads(row[5]),
        result=None if row[6] is None else result_from_json(row[1], row[6]),
        error_code=row[7], error_message=row[8], created_at=row[9], ended_at=row[10])
