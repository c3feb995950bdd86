"""Alarms: every failed, fault-cancelled or interrupted job, every succeeded job whose result
is inconsistent (its ``consistency`` verdict, cell.vision.consistency) and every fault
(protective or emergency stop, arm or camera lost, gripper fault) becomes an alarm that stays
until an operator acknowledges it.

Why a log of its own: in the job list a failed approach is one row among many, below the
fold; a production cell needs something that stays on screen until a person has seen it, and
that survives a restart (the alarms live in the job database, table ``alarms``).

The alarms are derived, not reported: twice a second the log reads the jobs that ended badly
from the job table and the faults from the cell's status, so no code path of the cell has to
remember to raise one. (It polls rather than subscribing to the event bus on purpose: a
subscriber keeps the cell's monitor publishing state at camera rate, which costs CPU and GIL
time the motion threads need on a small cell PC.) New alarms are published on the event bus
(``alarm`` events). A fault raises one alarm when it appears, not one per poll; it may be
acknowledged while it lasts, and raises a new alarm when it comes back after clearing.
"""

from __future__ import annotations

import logging
import sqlite3
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from cell.error_codes import ErrorCode
from cell.errors import NotFoundError
from cell.jobs.events import EventBus
from cell.jobs.store import JobStore
from cell.results.approach import ApproachBase
from cell.results.check import CheckResult
from cell.results.jobs import result_from_json

log = logging.getLogger(__name__)

EVENT = "alarm"
ALARMED_JOB_STATES = ("failed", "cancelled", "interrupted")
# A job a person (or PLC) stopped on purpose ends "cancelled" with this code: an info event
# in the job history, the audit log and the ``stop`` event, not an alarm to acknowledge.
# A stop forced by a fault carries the fault's code and stays an alarm.
STOPPED_ON_REQUEST_CODE = "cancelled"

_SCHEMA = """
CREATE TABLE IF NOT EXISTS alarms (
    id INTEGER PRIMARY KEY AUTOINCREMENT,
    key TEXT NOT NULL UNIQUE,
    source TEXT NOT NULL,
    code TEXT NOT NULL,
    message TEXT NOT NULL,
    job_id TEXT,
    raised_at REAL NOT NULL,
    acked_at REAL,
    acked_by TEXT
);
CREATE INDEX IF NOT EXISTS alarms_active ON alarms (acked_at);
CREATE TABLE IF NOT EXISTS alarm_meta (key TEXT PRIMARY KEY, value REAL NOT NULL);
"""


@dataclass(frozen=True)
class Alarm:
    id: int
    source: str  # job, arm, camera, gripper, calibration
    code: str
    message: str
    job_id: str | None
    raised_at: float
    acknowledged_at: float | None
    acknowledged_by: str | None

    @property
    def active(self) -> bool:
        return self.acknowledged_at is None

    def as_dict(self) -> dict[str, Any]:
        return {"id": self.id, "source": self.source, "code": self.code,
                "message": self.message, "job_id": self.job_id, "raised_at": self.raised_at,
                "active": self.active, "acknowledged_at": self.acknowledged_at,
                "acknowledged_by": self.acknowledged_by}


def faults_in(status: dict[str, Any]) -> dict[str, tuple[str, str]]:
    """The faults a ``Cell.status()`` answer shows: code -> (source, message in words)."""
    out: dict[str, tuple[str, str]] = {}
    robot = status.get("robot") or {}
    if not robot.get("connected", False):
        out["arm_disconnected"] = ("arm", "the arm is not connected"
                                   + (f": {robot['error']}" if robot.get("error") else ""))
    elif status.get("state") == "emergency_stop":
        out["emergency_stop"] = ("arm", "emergency stop: release the e-stop, then unlock and "
                                 "power on the arm")
    elif robot.get("protective_stop"):
        out["protective_stop"] = ("arm", "protective stop: check the cell, then unlock the "
                                  "protective stop")
    camera = status.get("camera") or {}
    if not camera.get("connected", True):
        out["camera_lost"] = ("camera", "the camera is not delivering frames (lost or "
                              "unplugged); locate and approach are refused")
    gripper = status.get("gripper") or {}
    problem = gripper.get("fault") or gripper.get("error")
    if problem:
        out["gripper_fault"] = ("gripper", f"gripper: {problem}")
    return out


class AlarmLog:
    """The cell's alarms, persisted beside its ``jobs``, published on its ``events``; the
    faults are read from ``status`` (``Cell.status``). ``start()`` begins watching."""

    def __init__(self, jobs: JobStore, events: EventBus, status: Callable[[], dict[str, Any]],
                 poll_s: float = 0.5) -> None:
        self.jobs = jobs
        self.events = events
        self.status = status
        self.poll_s = poll_s
        path = str(jobs.path)
        self._db = sqlite3.connect(path, check_same_thread=False, isolation_level=None,
                                   timeout=10.0)
        self._db.execute("PRAGMA journal_mode=WAL")
        self._db.executescript(_SCHEMA)
        self._lock = threading.Lock()
        with self._lock:
            self._db.execute("INSERT OR IGNORE INTO alarm_meta (key, value) VALUES "
                             "('jobs_since', ?)", (time.time(),))
            # jobs that ended before the alarm log existed are history, not alarms
            self._jobs_since = float(self._db.execute(
                "SELECT value FROM alarm_meta WHERE key = 'jobs_since'").fetchone()[0])
        # faults already alarmed and unacknowledged count as seen: no duplicate on restart
        self._present: set[str] = {a.code for a in self.list(active_only=True, limit=1000)[0]
                                   if a.source != "job"}
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None

    # -- watching ------------------------------------------------------------------------------
    def start(self) -> None:
        if self._thread is None:
            self._thread = threading.Thread(target=self._run, name="cell-alarms", daemon=True)
            self._thread.start()

    def close(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=5.0)
        with self._lock:
            self._db.close()

    def _run(self) -> None:
        last_error_s = -1e9
        while not self._stop.wait(self.poll_s):
            try:
                self.check()
            except Exception:  # a bad read must never end the watching
                if time.monotonic() - last_error_s > 60.0:  # and must not flood the log
                    last_error_s = time.monotonic()
                    log.exception("alarm check failed")

    def check(self) -> list[Alarm]:
        """Raise what is new: finished jobs that failed, faults that appeared."""
        raised = []
        for job_id, kind, state, code, words, ended in self._ended_jobs():
            alarm = self._raise(f"job:{job_id}", "job", code or state,
                                f"{kind.replace('_', ' ')} job {job_id} {state}: "
                                f"{words or state}", job_id, ended)
            if alarm is not None:
                raised.append(alarm)
        raised += self.check_drift()
        for job_id, kind, code, words, ended in self._inconsistent_jobs():
            alarm = self._raise(f"consistency:{job_id}", "job", code,
                                f"{kind.replace('_', ' ')} job {job_id} succeeded, but its "
                                f"result is inconsistent: {words}", job_id, ended)
            if alarm is not None:
                raised.append(alarm)
        faults = faults_in(self.status())
        for code, (source, message) in faults.items():
            if code not in self._present:
                alarm = self._raise(f"fault:{code}:{time.time_ns()}", source, code, message)
                if alarm is not None:
                    raised.append(alarm)
        self._present = set(faults)
        return raised

    def check_drift(self) -> list[Alarm]:
        """Raise ``calibration_drift`` for each calibration check that said ``drifted`` and has
        no alarm yet (also called before a job the drift policy may refuse, so a check that
        just ended counts at once)."""
        raised = []
        for job_id, result, ended in self._drifted_checks():
            alarm = self._raise(
                f"drift:{job_id}", "calibration", ErrorCode.calibration_drift,
                f"calibration check {job_id}: drifted by {result.tcp_error_mm:.3f} mm / "
                f"{result.tcp_error_deg:.3f} deg at the tool (tolerance "
                f"{result.tolerance_mm:g} mm / {result.tolerance_deg:g} deg); re-calibrate, or "
                "acknowledge if the cell is fine", job_id, ended)
            if alarm is not None:
                raised.append(alarm)
        return raised

    def active_drift(self) -> Alarm | None:
        """The newest unacknowledged ``calibration_drift`` alarm, if any."""
        with self._lock:
            row = self._db.execute(
                f"{_SELECT} WHERE acked_at IS NULL AND code = ? ORDER BY id DESC LIMIT 1",
                (ErrorCode.calibration_drift.value,)).fetchone()
        return None if row is None else _alarm(row)

    def _drifted_checks(self) -> list[tuple[str, CheckResult, float]]:
        if str(self.jobs.path) == ":memory:":
            rows = [(j.id, j.result, j.ended_at) for j in self.jobs.list_jobs(50)
                    if j.kind == "calibration_check" and j.state == "succeeded"
                    and (j.ended_at or 0) >= self._jobs_since]
            jobs = [(i, r, e) for i, r, e in rows if isinstance(r, CheckResult)]
        else:
            with self._lock:
                found = self._db.execute(
                    "SELECT id, result, ended_at FROM jobs WHERE kind = 'calibration_check' "
                    "AND state = 'succeeded' AND ended_at >= ? "
                    "AND 'drift:' || id NOT IN (SELECT key FROM alarms WHERE "
                    "source = 'calibration') ORDER BY ended_at", (self._jobs_since,)).fetchall()
            jobs = []
            for i, r, e in found:
                result = result_from_json("calibration_check", r) if r else None
                if isinstance(result, CheckResult):
                    jobs.append((i, result, e))
        return [(i, r, float(e or 0)) for i, r, e in jobs if r.verdict == "drifted"]

    def _ended_jobs(self) -> list[tuple[Any, ...]]:
        """Jobs that ended badly since the log began and have no alarm yet (the job table is
        in the same database file; an in-memory store is read through its own API)."""
        if str(self.jobs.path) == ":memory:":
            return [(j.id, j.kind, j.state, j.error_code, j.error_message, j.ended_at)
                    for j in self.jobs.list_jobs(50)
                    if j.state in ALARMED_JOB_STATES and (j.ended_at or 0) >= self._jobs_since
                    and not (j.state == "cancelled"
                             and j.error_code == STOPPED_ON_REQUEST_CODE)]
        with self._lock:
            return self._db.execute(
                "SELECT id, kind, state, error_code, error_message, ended_at FROM jobs "
                "WHERE state IN ('failed', 'cancelled', 'interrupted') AND ended_at >= ? "
                "AND NOT (state = 'cancelled' AND IFNULL(error_code, '') = ?) "
                "AND 'job:' || id NOT IN (SELECT key FROM alarms WHERE source = 'job') "
                "ORDER BY ended_at", (self._jobs_since, STOPPED_ON_REQUEST_CODE)).fetchall()

    def _inconsistent_jobs(self) -> list[tuple[Any, ...]]:
        """Succeeded jobs whose ``consistency`` verdict is inconsistent (a mount error leaves
        the arm where the calibration says, not where the target is) and have no alarm yet:
        ``(id, kind, code, finding, ended_at)``."""
        if str(self.jobs.path) == ":memory:":
            jobs = [(j.id, j.kind, j.result, j.ended_at) for j in self.jobs.list_jobs(50)
                    if j.state == "succeeded" and (j.ended_at or 0) >= self._jobs_since]
        else:
            with self._lock:
                rows = self._db.execute(
                    "SELECT id, kind, result, ended_at FROM jobs WHERE state = 'succeeded' "
                    "AND ended_at >= ? AND result LIKE '%\"inconsistent\"%' "
                    "AND 'consistency:' || id NOT IN (SELECT key FROM alarms WHERE "
                    "source = 'job') ORDER BY ended_at", (self._jobs_since,)).fetchall()
            jobs = [(i, k, result_from_json(k, r) if r else None, e) for i, k, r, e in rows]
        out = []
        for job_id, kind, result, ended in jobs:
            if isinstance(result, ApproachBase) and result.consistency.verdict == "inconsistent":
                c = result.consistency
                codes, findings = c.codes or ["calibration_inconsistent"], c.findings or [""]
                out.append((job_id, kind, codes[-1], findings[-1], ended))
        return out

    def _raise(self, key: str, source: str, code: str, message: str,
               job_id: str | None = None, at: float | None = None) -> Alarm | None:
        with self._lock:
            cur = self._db.execute(
                "INSERT OR IGNORE INTO alarms (key, source, code, message, job_id, raised_at) "
                "VALUES (?, ?, ?, ?, ?, ?)",
                (key, source, code, message, job_id, time.time() if at is None else at))
            if cur.rowcount == 0:
                return None
            alarm = self._get_locked(int(cur.lastrowid or 0))
        log.warning("alarm %d (%s): %s", alarm.id, alarm.code, alarm.message)
        self.events.publish(EVENT, {"alarm": alarm.as_dict()})
        return alarm

    # -- reading and acknowledging ---------------------------------------------------------
    def list(self, active_only: bool = False, limit: int = 50,
             offset: int = 0) -> tuple[list[Alarm], int, int]:
        """(alarms newest first, how many match, how many are active)."""
        where = "WHERE acked_at IS NULL" if active_only else ""
        with self._lock:
            rows = self._db.execute(
                f"{_SELECT} {where} ORDER BY id DESC LIMIT ? OFFSET ?",
                (limit, offset)).fetchall()
            total = self._db.execute(f"SELECT COUNT(*) FROM alarms {where}").fetchone()[0]
            active = self._db.execute(
                "SELECT COUNT(*) FROM alarms WHERE acked_at IS NULL").fetchone()[0]
        return [_alarm(r) for r in rows], int(total), int(active)

    def get(self, alarm_id: int) -> Alarm:
        with self._lock:
            return self._get_locked(alarm_id)

    def _get_locked(self, alarm_id: int) -> Alarm:
        row = None if not 0 < alarm_id < 2**63 else (  # SQLite's integers are 64-bit
            self._db.execute(f"{_SELECT} WHERE id = ?", (alarm_id,)).fetchone())
        if row is None:
            raise NotFoundError(ErrorCode.alarm_not_found, f"no alarm with id {alarm_id}")
        return _alarm(row)

    def acknowledge(self, alarm_id: int, caller: str) -> Alarm:
        """Mark seen (audited). Acknowledging twice keeps the first acknowledgement."""
        t0 = time.time()
        try:
            with self._lock:
                self._get_locked(alarm_id)
                self._db.execute("UPDATE alarms SET acked_at = ?, acked_by = ? WHERE id = ? "
                                 "AND acked_at IS NULL", (t0, caller, alarm_id))
                alarm = self._get_locked(alarm_id)
        except NotFoundError as err:
            self.jobs.audit(caller, "alarm_ack", {"id": alarm_id},
                                 f"refused:{err.code}", err.message, None, t0)
            raise
        first = alarm.acknowledged_by == caller and alarm.acknowledged_at == t0
        self.jobs.audit(caller, "alarm_ack", {"id": alarm_id, "code": alarm.code}, "ok",
                             "" if first else "already acknowledged", alarm.job_id, t0)
        self.events.publish(EVENT, {"alarm": alarm.as_dict()})
        return alarm


_SELECT = ("SELECT id, source, code, message, job_id, raised_at, acked_at, acked_by "
           "FROM alarms")


def _alarm(row: tuple[Any, ...]) -> Alarm:
    return Alarm(int(row[0]), row[1], row[2], row[3], row[4], float(row[5]), row[6], row[7])
