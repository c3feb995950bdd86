"""The alarm watch against a real job database: each bad end alarmed once, across restarts,
from the ends since its last poll only; a database that takes no writes is the
``storage_failed`` alarm, kept in memory (listed, acknowledged) and written with its id once
writes work again."""

from __future__ import annotations

import sqlite3
from pathlib import Path
from typing import Any

from cell.features.alarms import AlarmLog
from cell.jobs.events import EventBus
from cell.jobs.store import JobStore

HEALTHY: dict[str, Any] = {"robot": {"connected": True}, "camera": {"connected": True}}


def _failed_job(store: JobStore) -> str:
    job = store.create("approach", "plc", {})
    store.finish(job.id, "failed", None, "target_lost", "the target left the view")
    return job.id


def _stored(path: Path) -> list[tuple[Any, ...]]:
    con = sqlite3.connect(path)
    rows = con.execute("SELECT id, code, job_id, acked_by FROM alarms ORDER BY id").fetchall()
    con.close()
    return rows


def test_each_bad_end_is_alarmed_once_across_a_restart(tmp_path: Path) -> None:
    store = JobStore(tmp_path / "jobs.db")
    alarms = AlarmLog(store, EventBus(), lambda: HEALTHY)
    first = _failed_job(store)
    stopped = store.create("home", "operator", {})
    store.finish(stopped.id, "cancelled", None, "cancelled", "stopped by request")
    assert [a.job_id for a in alarms.check()] == [first]
    assert alarms.check() == []
    alarms.close()
    store.close()

    store = JobStore(tmp_path / "jobs.db")
    alarms = AlarmLog(store, EventBus(), lambda: HEALTHY)
    assert alarms.check() == []  # judged by the run before: not alarmed again
    second = _failed_job(store)
    assert [a.job_id for a in alarms.check()] == [second]
    assert [r[2] for r in _stored(tmp_path / "jobs.db")] == [first, second]
    alarms.close()
    store.close()


def test_a_database_without_writes_is_an_alarm_kept_until_it_can_be_written(
        tmp_path: Path) -> None:
    path = tmp_path / "jobs.db"
    store = JobStore(path)
    alarms = AlarmLog(store, EventBus(), lambda: HEALTHY)
    writable = (store._db, alarms._db)
    for holder in (store, alarms):
        holder._db = sqlite3.connect(f"file:{path}?mode=ro", uri=True, check_same_thread=False,
                                     isolation_level=None)
    store.probe()
    raised = alarms.check()
    assert [(a.code, a.source) for a in raised] == [("storage_failed", "storage")]
    assert alarms.check() == []  # one alarm while the fault lasts
    kept = raised[0]
    listed, total, active = alarms.list()
    assert [a.id for a in listed] == [kept.id] and total == active == 1
    assert alarms.acknowledge(kept.id, "operator").acknowledged_by == "operator"
    assert _stored(path) == []

    for holder, db in zip((store, alarms), writable, strict=True):
        holder._db.close()
        holder._db = db
    assert store.probe() is None
    alarms.check()
    assert _stored(path) == [(kept.id, "storage_failed", None, "operator")]
    assert alarms.list()[1] == 1 and alarms.list()[2] == 0
    alarms.close()
    store.close()
