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

Each poll reads only the jobs that ended since the last one (an index range over ``ended_at``
from a mark kept in ``alarm_meta``), so a database of months costs what a fresh one does. A job
database that cannot be written is the fault ``storage_failed``; alarms that cannot be written
meanwhile are kept in memory (listed, acknowledged, published as any other) and written when
the database takes writes again.
"""

from __future__ import annotations

import logging
import sqlite3
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, replace
from typing import Any

from cell.error_codes import ErrorCode
from cell.errors import NotFoundError
from cell.jobs.events import EventBus
from cell.jobs.store import Job, JobStore
from cell.results.approach import ApproachBase
from cell.results.check import CheckResult

log = logging.getLogger(__name__)

EVENT = "alarm"
ALARMED_JOB_STATES = ("failed", "cancelled", "interrupted")
# A job a person (or PLC) stopped on purpose ends "cancelled" with this code: an info event
# in the job history, the audit log and the ``stop`` event, not an alarm to acknowledge.
# A stop forced by a fault carries the fault's code and stays an alarm.
STOPPED_ON_REQUEST_CODE = "cancelled"
# Jobs that ended this long before the newest end seen are read again on the next poll: a job
# whose end was written late (a slow commit, a clock step) is not missed.
OVERLAP_S = 5.0
# A database whose alarm log kept no mark yet (written by a version that judged every poll
# from the start): ends older than this were judged by that version while it ran.
FIRST_LOOK_BACK_S = 3600.0

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
    source: str  # job, arm, camera, gripper, calibration, storage
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


LINK_FAULTS = ("arm_disconnected", "camera_lost")  # a device's link down (not at start)


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


def storage_fault(write_error: str | None) -> dict[str, tuple[str, str]]:
    """``storage_failed`` while the job database cannot be written."""
    if write_error is None:
        return {}
    return {ErrorCode.storage_failed.value: (
        "storage", f"the job database cannot be written ({write_error}): new jobs are "
        "refused and job ends are kept in memory until it can; free space on the disk")}


class AlarmLog:
    """The cell's alarms, persisted beside its ``jobs``, published on its ``events``; the
    faults are read from ``status`` (``Cell.status``). ``start()`` begins watching."""

    def __init__(self, jobs: JobStore, events: EventBus, status: Callable[[], dict[str, Any]],
                 poll_s: float = 0.5, starting: Callable[[], bool] = lambda: False) -> None:
        """``starting``: true while the service's first connect runs; a device not yet
        connected then is not lost (its alarm is raised if it is still missing after)."""
        self.jobs = jobs
        self.events = events
        self.status = status
        self.starting = starting
        self.poll_s = poll_s
        path = str(jobs.path)
        self._db = sqlite3.connect(path, check_same_thread=False, isolation_level=None,
                                   timeout=10.0)
        self._db.execute("PRAGMA journal_mode=WAL")
        self._db.executescript(_SCHEMA)
        self._lock = threading.Lock()
        # alarms that could not be written: id -> (key, alarm), written when writes work again
        self._unsaved: dict[int, tuple[str, Alarm]] = {}
        now = time.time()
        with self._lock:
            try:
                self._db.execute("INSERT OR IGNORE INTO alarm_meta (key, value) VALUES "
                                 "('jobs_since', ?)", (now,))
            except sqlite3.Error as err:
                log.error("the alarm log cannot be written: %s", err)
            meta = dict(self._db.execute("SELECT key, value FROM alarm_meta"))
        # jobs that ended before the alarm log existed are history, not alarms; ends read
        # up to 'jobs_seen' were judged by an earlier run
        self._jobs_since = float(meta.get("jobs_since", now))
        self._seen_until = float(meta["jobs_seen"]) if "jobs_seen" in meta else \
            max(self._jobs_since, now - FIRST_LOOK_BACK_S)
        self._seen_saved = self._seen_until
        self._handled: dict[str, float] = {}  # job id -> its end, within the overlap
        # faults already alarmed and unacknowledged count as seen: no duplicate on restart
        self._present: set[str] = {a.code for a in self.list(active_only=True, limit=1000)[0]
                                   if a.source not in ("job", "calibration")}
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
        if self._unsaved and self.jobs.write_error is None:
            self._flush()
        raised = []
        ended = self._newly_ended()
        for job in ended:
            if job.state in ALARMED_JOB_STATES and not (
                    job.state == "cancelled" and job.error_code == STOPPED_ON_REQUEST_CODE):
                raised += self._raised(
                    f"job:{job.id}", "job", job.error_code or job.state,
                    f"{job.kind.replace('_', ' ')} job {job.id} {job.state}: "
                    f"{job.error_message or job.state}", job.id, job.ended_at)
        raised += self._drift_alarms(ended)
        for job_id, kind, code, words, at in _inconsistent(ended):
            raised += self._raised(f"consistency:{job_id}", "job", code,
                                   f"{kind.replace('_', ' ')} job {job_id} succeeded, but its "
                                   f"result is inconsistent: {words}", job_id, at)
        self._mark_seen(ended)
        faults = {**faults_in(self.status()), **storage_fault(self.jobs.write_error)}
        if self.starting():
            faults = {c: f for c, f in faults.items() if c not in LINK_FAULTS}
        for code, (source, message) in faults.items():
            if code not in self._present:
                raised += self._raised(f"fault:{code}:{time.time_ns()}", source, code, message)
        self._present = set(faults)
        return raised

    def check_drift(self) -> list[Alarm]:
        """Raise ``calibration_drift`` for each calibration check that said ``drifted`` and has
        no alarm yet (also called before a job the drift policy may refuse, so a check that
        just ended counts at once)."""
        recent = [j for j in self.jobs.ended_since(self._seen_until - OVERLAP_S)
                  if j.ended_at is not None and j.ended_at >= self._jobs_since]
        return self._drift_alarms(recent)

    def _drift_alarms(self, ended: list[Job]) -> list[Alarm]:
        raised = []
        for job in ended:
            result = job.result
            if job.kind == "calibration_check" and job.state == "succeeded" \
                    and isinstance(result, CheckResult) and result.verdict == "drifted":
                raised += self._raised(
                    f"drift:{job.id}", "calibration", ErrorCode.calibration_drift,
                    f"calibration check {job.id}: drifted by {result.tcp_error_mm:.3f} mm / "
                    f"{result.tcp_error_deg:.3f} deg at the tool (tolerance "
                    f"{result.tolerance_mm:g} mm / {result.tolerance_deg:g} deg); "
                    "re-calibrate, or acknowledge if the cell is fine", job.id, job.ended_at)
        return raised

    def active_drift(self) -> Alarm | None:
        """The newest unacknowledged ``calibration_drift`` alarm, if any."""
        code = ErrorCode.calibration_drift.value
        kept = [a for _, a in self._unsaved.values() if a.code == code and a.active]
        if kept:
            return max(kept, key=lambda a: a.id)
        with self._lock:
            row = self._db.execute(
                f"{_SELECT} WHERE acked_at IS NULL AND code = ? ORDER BY id DESC LIMIT 1",
                (code,)).fetchone()
        return None if row is None else _alarm(row)

    def _newly_ended(self) -> list[Job]:
        """Jobs that ended since the last poll (and since the log began) not judged yet."""
        jobs = self.jobs.ended_since(max(self._jobs_since, self._seen_until - OVERLAP_S))
        return [j for j in jobs if j.id not in self._handled]

    def _mark_seen(self, ended: list[Job]) -> None:
        """Remember the judged ends; the mark is saved so a restart does not judge again."""
        for job in ended:
            self._handled[job.id] = job.ended_at or 0.0
            self._seen_until = max(self._seen_until, job.ended_at or 0.0)
        horizon = self._seen_until - 2 * OVERLAP_S
        self._handled = {i: t for i, t in self._handled.items() if t >= horizon}
        if self._seen_until > self._seen_saved and self.jobs.write_error is None:
            with self._lock:
                try:
                    self._db.execute("INSERT OR REPLACE INTO alarm_meta (key, value) VALUES "
                                     "('jobs_seen', ?)", (self._seen_until,))
                    self._seen_saved = self._seen_until
                except sqlite3.Error as err:
                    log.warning("could not save the alarm log's mark: %s", err)

    def _raised(self, key: str, source: str, code: str, message: str,
                job_id: str | None = None, at: float | None = None) -> list[Alarm]:
        alarm = self._raise(key, source, code, message, job_id, at)
        return [] if alarm is None else [alarm]

    def _raise(self, key: str, source: str, code: str, message: str,
               job_id: str | None = None, at: float | None = None) -> Alarm | None:
        raised_at = time.time() if at is None else at
        with self._lock:
            if any(k == key for k, _ in self._unsaved.values()):
                return None
            try:
                cur = self._db.execute(
                    "INSERT OR IGNORE INTO alarms (key, source, code, message, job_id, "
                    "raised_at) VALUES (?, ?, ?, ?, ?, ?)",
                    (key, source, code, message, job_id, raised_at))
            except sqlite3.Error as err:
                alarm = Alarm(self._next_id_locked(), source, code, message, job_id,
                              raised_at, None, None)
                self._unsaved[alarm.id] = (key, alarm)
                log.error("alarm %d kept in memory, the database cannot be written: %s",
                          alarm.id, err)
            else:
                if cur.rowcount == 0:
                    return None
                alarm = self._get_locked(int(cur.lastrowid or 0))
        log.warning("alarm %d (%s): %s", alarm.id, alarm.code, alarm.message)
        self.events.publish(EVENT, {"alarm": alarm.as_dict()})
        return alarm

    def _next_id_locked(self) -> int:
        stored = self._db.execute("SELECT IFNULL(MAX(id), 0) FROM alarms").fetchone()[0]
        return max([int(stored), *self._unsaved]) + 1

    def _flush(self) -> None:
        """Write the alarms kept in memory (with their ids); kept when it fails."""
        with self._lock:
            kept = list(self._unsaved.items())
            try:
                self._db.execute("BEGIN IMMEDIATE")
                for alarm_id, (key, a) in kept:
                    self._db.execute(
                        "INSERT OR IGNORE INTO alarms (id, key, source, code, message, job_id, "
                        "raised_at, acked_at, acked_by) VALUES (?, ?, ?, ?, ?, ?, ?, ?, ?)",
                        (alarm_id, key, a.source, a.code, a.message, a.job_id, a.raised_at,
                         a.acknowledged_at, a.acknowledged_by))
                self._db.execute("COMMIT")
            except sqlite3.Error as err:
                if self._db.in_transaction:
                    self._db.execute("ROLLBACK")
                log.debug("alarms still kept in memory: %s", err)
                return
            for alarm_id, _ in kept:
                self._unsaved.pop(alarm_id, None)
        log.warning("%d alarms kept in memory are written", len(kept))

    def prune(self, acked_before_s: float, limit: int) -> int:
        """Delete up to ``limit`` alarms acknowledged before UNIX time ``acked_before_s``,
        oldest acknowledgement first (an active alarm is never deleted); how many went."""
        with self._lock:
            cur = self._db.execute(
                "DELETE FROM alarms WHERE id IN (SELECT id FROM alarms WHERE acked_at < ? "
                "ORDER BY acked_at LIMIT ?)", (acked_before_s, limit))
            return max(0, cur.rowcount)

    # -- reading and acknowledging ---------------------------------------------------------
    def list(self, active_only: bool = False, limit: int = 50,
             offset: int = 0) -> tuple[list[Alarm], int, int]:
        """(alarms newest first, how many match, how many are active)."""
        kept = sorted((a for _, a in self._unsaved.values() if a.active or not active_only),
                      key=lambda a: -a.id)
        shown = kept[offset:offset + limit]
        where = "WHERE acked_at IS NULL" if active_only else ""
        with self._lock:
            rows = self._db.execute(
                f"{_SELECT} {where} ORDER BY id DESC LIMIT ? OFFSET ?",
                (limit - len(shown), max(0, offset - len(kept)))).fetchall()
            total = self._db.execute(f"SELECT COUNT(*) FROM alarms {where}").fetchone()[0]
            active = self._db.execute(
                "SELECT COUNT(*) FROM alarms WHERE acked_at IS NULL").fetchone()[0]
        n_active = sum(1 for _, a in self._unsaved.values() if a.active)
        return (shown + [_alarm(r) for r in rows], int(total) + len(kept),
                int(active) + n_active)

    def get(self, alarm_id: int) -> Alarm:
        with self._lock:
            return self._get_locked(alarm_id)

    def _get_locked(self, alarm_id: int) -> Alarm:
        if alarm_id in self._unsaved:
            return self._unsaved[alarm_id][1]
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
                alarm = self._get_locked(alarm_id)
                if alarm_id in self._unsaved:
                    if alarm.active:
                        alarm = replace(alarm, acknowledged_at=t0, acknowledged_by=caller)
                        self._unsaved[alarm_id] = (self._unsaved[alarm_id][0], alarm)
                else:
                    self._db.execute("UPDATE alarms SET acked_at = ?, acked_by = ? WHERE "
                                     "id = ? AND acked_at IS NULL", (t0, caller, alarm_id))
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


def _inconsistent(ended: list[Job]) -> list[tuple[str, str, str, str, float | None]]:
    """Succeeded jobs whose ``consistency`` verdict is inconsistent (a mount error leaves the
    arm where the calibration says, not where the target is): ``(id, kind, code, finding,
    ended_at)``."""
    out = []
    for job in ended:
        result = job.result
        if job.state == "succeeded" and isinstance(result, ApproachBase) \
                and result.consistency.verdict == "inconsistent":
            c = result.consistency
            codes, findings = c.codes or ["calibration_inconsistent"], c.findings or [""]
            out.append((job.id, job.kind, codes[-1], findings[-1], job.ended_at))
    return out


_SELECT = ("SELECT id, source, code, message, job_id, raised_at, acked_at, acked_by "
           "FROM alarms")


def _alarm(row: tuple[Any, ...]) -> Alarm:
    return Alarm(int(row[0]), row[1], row[2], row[3], row[4], float(row[5]), row[6], row[7])
