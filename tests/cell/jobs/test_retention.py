"""Retention of the job database and the image log: what goes by age and by size, what never
goes (running jobs, active alarms, the hand-eye calibration's job), the file shrinking on disk,
and every periodic query of the store and the alarm watch answered through an index."""

from __future__ import annotations

import json
import os
import sqlite3
import time
from pathlib import Path

import numpy as np

from cell.config.schema import RetentionConfig
from cell.features.alarms import AlarmLog
from cell.jobs.events import EventBus
from cell.jobs.store import JobStore, Pruning
from cell.supervision.retention import DAY_S, Retention
from cell.vision.imagelog import ImageLog

PARAMS = {"standoff_mm": 80.0, "recipe": "", "note": "x" * 2000}  # a few KB a row, like results


def _store(tmp_path: Path) -> JobStore:
    return JobStore(tmp_path / "jobs.db")


def _age(store: JobStore, days: float) -> None:
    """Every row written so far as if written ``days`` ago."""
    shift = days * DAY_S
    db = sqlite3.connect(store.path)
    with db:
        db.execute("UPDATE jobs SET created_at = created_at - ?, ended_at = ended_at - ?",
                   (shift, shift))
        db.execute("UPDATE audit SET started_at = started_at - ?, ended_at = ended_at - ?",
                   (shift, shift))
    db.close()


def _jobs(store: JobStore, n: int, kind: str = "approach") -> list[str]:
    ids = []
    for _ in range(n):
        job = store.create(kind, "plc", PARAMS)
        store.audit("plc", kind, PARAMS, "ok", "started", job.id)
        store.finish(job.id, "failed", None, "target_lost", "the target left the view")
        ids.append(job.id)
    return ids


def _count(store: JobStore, table: str) -> int:
    db = sqlite3.connect(store.path)
    n = int(db.execute(f"SELECT COUNT(*) FROM {table}").fetchone()[0])
    db.close()
    return n


def test_by_age_old_rows_go_running_jobs_and_the_calibration_stay(tmp_path: Path) -> None:
    store = _store(tmp_path)
    old = _jobs(store, 30)
    running = store.create("track", "plc", PARAMS)
    calibration = store.create("calibration", "operator", {})
    store.finish(calibration.id, "failed", None, "cancelled", "stopped")
    _age(store, 200)
    new = _jobs(store, 5)
    retention = Retention(RetentionConfig(jobs_days=180, audit_days=180, batch_rows=7),
                          store, lambda before, n: 0)
    out = retention.run_once()
    assert out.jobs == 30 and out.audit == 30  # every old row, in batches of 7
    assert all(store.get(i) is None for i in old)
    assert all(store.get(i) is not None for i in new)
    assert store.get(running.id) is not None and store.get(calibration.id) is not None
    assert _count(store, "audit") == 5
    store.close()


def test_by_size_the_oldest_jobs_go_first_and_the_file_shrinks(tmp_path: Path) -> None:
    store = _store(tmp_path)
    ids = _jobs(store, 1500)
    size_before = store.path.stat().st_size
    assert size_before > 5 * 1024 * 1024
    max_mb = 0.7 * Pruning(store).used_bytes() / 1024 / 1024
    retention = Retention(RetentionConfig(database_max_mb=max_mb, batch_rows=100), store,
                          lambda before, n: 0)
    out = retention.run_once()
    assert out.used_bytes <= max_mb * 1024 * 1024
    assert 500 < out.jobs < 1500 and out.audit == 0 and out.released_pages > 0
    kept = [i for i in ids if store.get(i) is not None]
    assert kept == ids[len(ids) - len(kept):]  # the newest stayed
    assert store.path.stat().st_size < 0.8 * size_before, (size_before, store.path.stat())
    store.close()


def test_acknowledged_alarms_go_by_age_active_ones_never(tmp_path: Path) -> None:
    store = _store(tmp_path)
    alarms = AlarmLog(store, EventBus(), lambda: {"robot": {"connected": True}})
    _jobs(store, 4)
    raised = alarms.check()
    assert len(raised) == 4
    alarms.acknowledge(raised[0].id, "operator")
    alarms.acknowledge(raised[1].id, "operator")
    retention = Retention(RetentionConfig(alarms_days=30), store, alarms.prune)
    assert retention.run_once(now_s=time.time() + 31 * DAY_S).alarms == 2
    left, total, active = alarms.list(limit=10)
    assert {a.id for a in left} == {raised[2].id, raised[3].id} and total == active == 2
    alarms.close()
    store.close()


def test_the_image_log_by_age_and_by_size(tmp_path: Path) -> None:
    log = ImageLog(tmp_path / "images", max_entries=100)
    rng = np.random.default_rng(0)
    for _ in range(6):
        log.save(rng.integers(0, 255, (120, 160), dtype=np.uint8), {"code": "too_few_blobs"})
    pngs = log.entries()
    each = pngs[0].stat().st_size
    old = time.time() - 100 * DAY_S
    for png in pngs[:2]:
        os.utime(png, (old, old))
    config = RetentionConfig(images_days=90, images_max_mb=3.5 * each / 1024 / 1024)
    store = JobStore(":memory:")
    out = Retention(config, store, lambda before, n: 0, log).run_once()
    assert out.images == 3  # two by age, one more to fit the size
    assert [p.name for p in log.entries()] == [p.name for p in pngs[3:]]
    assert not list((tmp_path / "images").glob(f"{pngs[0].stem}*"))


def test_periodic_queries_use_an_index(tmp_path: Path) -> None:
    store = _store(tmp_path)
    AlarmLog(store, EventBus(), lambda: {}).close()
    db = sqlite3.connect(store.path)
    queries = [
        ("SELECT * FROM jobs WHERE ended_at >= ? ORDER BY ended_at", (0.0,)),
        ("SELECT * FROM jobs WHERE state = 'running'", ()),
        ("SELECT * FROM jobs ORDER BY created_at DESC, rowid DESC LIMIT 50", ()),
        ("SELECT * FROM jobs WHERE kind = ? ORDER BY created_at DESC LIMIT 1", ("x",)),
        ("SELECT COUNT(*) FROM jobs WHERE kind IN (?) AND created_at > ?", ("x", 0.0)),
        ("SELECT rowid FROM jobs WHERE created_at < ? AND state != 'running' "
         "ORDER BY created_at LIMIT 10", (0.0,)),
        ("SELECT id FROM alarms WHERE acked_at < ? ORDER BY acked_at LIMIT 10", (0.0,)),
        ("SELECT * FROM alarms WHERE acked_at IS NULL AND code = ? ORDER BY id DESC LIMIT 1",
         ("x",)),
    ]
    for sql, args in queries:
        steps = [str(r[-1]) for r in db.execute(f"EXPLAIN QUERY PLAN {sql}", args)]
        full_scans = [s for s in steps if s in ("SCAN jobs", "SCAN alarms")]
        assert not full_scans and any("INDEX" in s for s in steps), (sql, steps)
    db.close()
    store.close()


def test_a_database_made_without_incremental_vacuum_is_converted_when_idle(
        tmp_path: Path) -> None:
    path = tmp_path / "jobs.db"
    db = sqlite3.connect(path)
    db.execute("CREATE TABLE legacy (x)")  # the file exists before the store sets its mode
    db.close()
    store = JobStore(path)
    assert json.dumps(store._db.execute("PRAGMA auto_vacuum").fetchone()) == "[0]"
    _jobs(store, 20)
    busy = Retention(RetentionConfig(), store, lambda before, n: 0, idle=lambda: False)
    busy.run_once()
    assert store._db.execute("PRAGMA auto_vacuum").fetchone()[0] == 0
    Retention(RetentionConfig(), store, lambda before, n: 0).run_once()
    assert store._db.execute("PRAGMA auto_vacuum").fetchone()[0] == 2
    assert _count(store, "jobs") == 20
    store.close()
