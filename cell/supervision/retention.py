"""Retention: what the cell writes is deleted by age and by size, in the background.

Why: a cell runs for years on a small disk. Without a bound the job database grows by tens of
MB a day at a busy rate, and every query that is not an index range slows down as it ages.
Every ``[retention] period_s`` one pass deletes, in batches of ``batch_rows`` with a pause
between them (a job's writes never wait long for the store's lock):

1. by age: jobs created, audit rows ended and alarms acknowledged longer ago than their
   ``*_days``, and image log entries older than ``images_days``;
2. by size: while the database's used pages exceed ``database_max_mb``, the oldest jobs,
   then the oldest audit rows, then the oldest acknowledged alarms; the image log down to
   ``images_max_mb``;
3. the hand-eye routines' saved datasets beyond the newest ``calibration_datasets_keep``,
   never the calibration in use (:mod:`cell.supervision.dataset_retention`);
4. the freed pages are handed back to the file system (incremental vacuum) and the WAL is
   checkpointed, so the file shrinks. A database made before incremental vacuum is rewritten
   once for it, only while no motion holds the arm and only when small
   (``CONVERT_MAX_BYTES``): a larger one reuses its free pages (it stops growing) but shrinks
   only with an offline ``VACUUM``.

Every delete is a bounded index range (:class:`cell.jobs.store.Pruning`); nothing here scans
a table.
"""

from __future__ import annotations

import logging
import sqlite3
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

from cell.config.schema import RetentionConfig
from cell.jobs.store import JobStore, Pruning
from cell.supervision.dataset_retention import prune_datasets
from cell.vision.imagelog import ImageLog

log = logging.getLogger(__name__)
DAY_S = 86400.0
MB = 1024 * 1024
PAUSE_S = 0.05  # between batches: the store's lock is free for the jobs' writes
MAX_BATCHES = 200  # per table and pass: a backlog is worked off over several passes
RELEASE_PAGES = 256  # pages handed back per step of the incremental vacuum
CONVERT_MAX_BYTES = 256 * MB
KEEP_KINDS = ("calibration",)  # by age: the evidence of a hand-eye calibration stays

PruneAlarms = Callable[[float, int], int]  # (acknowledged before, limit) -> deleted


@dataclass
class Pass:
    """What one pass deleted (rows, entries) and the database's used bytes after it."""

    jobs: int = 0
    audit: int = 0
    alarms: int = 0
    images: int = 0
    datasets: int = 0
    released_pages: int = 0
    used_bytes: int = 0
    errors: list[str] = field(default_factory=list)


class Retention:
    def __init__(self, config: RetentionConfig, jobs: JobStore, prune_alarms: PruneAlarms,
                 images: ImageLog | None = None,
                 idle: Callable[[], bool] = lambda: True,
                 datasets: Path | None = None,
                 datasets_in_use: Callable[[], set[str]] = set) -> None:
        self.config = config
        self.pruning = Pruning(jobs)
        self.in_memory = str(jobs.path) == ":memory:"
        self.prune_alarms = prune_alarms
        self.images = images
        self.idle = idle
        self.datasets, self.datasets_in_use = datasets, datasets_in_use
        self.last: Pass | None = None
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None

    def start(self) -> None:
        self._thread = threading.Thread(target=self._loop, name="cell-retention", daemon=True)
        self._thread.start()

    def close(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=5.0)

    def _loop(self) -> None:
        while not self._stop.wait(self.config.period_s):
            try:
                self.run_once()
            except Exception:  # a bad pass must not end the retention
                log.exception("retention pass failed")

    def run_once(self, now_s: float | None = None) -> Pass:
        """One pass (see the module doc); a store that cannot be written ends it early."""
        now = time.time() if now_s is None else now_s
        c, out = self.config, Pass()
        try:
            if c.jobs_days:
                out.jobs += self._batches(lambda n: self.pruning.jobs(
                    now - c.jobs_days * DAY_S, n, KEEP_KINDS))
            if c.audit_days:
                out.audit += self._batches(lambda n: self.pruning.audit(
                    now - c.audit_days * DAY_S, n))
            if c.alarms_days:
                out.alarms += self._batches(lambda n: self.prune_alarms(
                    now - c.alarms_days * DAY_S, n))
            self._by_size(out)
            out.released_pages = self._release()
        except sqlite3.Error as err:
            out.errors.append(f"{type(err).__name__}: {err}")
            log.warning("retention pass stopped: %s", err)
        if self.images is not None:
            out.images = self.images.prune(now - c.images_days * DAY_S if c.images_days
                                           else float("-inf"), int(c.images_max_mb * MB))
        if self.datasets is not None:
            try:
                out.datasets = prune_datasets(self.datasets, c.calibration_datasets_keep,
                                              self.datasets_in_use())
            except (OSError, sqlite3.Error) as err:
                out.errors.append(f"{type(err).__name__}: {err}")
        out.used_bytes = 0 if self.in_memory else self.pruning.used_bytes()
        if out.jobs or out.audit or out.alarms or out.images or out.datasets:
            log.info("retention: deleted %d jobs, %d audit rows, %d alarms, %d images, "
                     "%d calibration datasets; database %.0f MB in use", out.jobs, out.audit,
                     out.alarms, out.images, out.datasets, out.used_bytes / MB)
        self.last = out
        return out

    def _by_size(self, out: Pass) -> None:
        if self.in_memory:
            return
        limit = self.config.database_max_mb * MB
        steps: list[tuple[str, Callable[[int], int]]] = [
            ("jobs", lambda n: self.pruning.jobs(float("inf"), n)),
            ("audit", lambda n: self.pruning.audit(float("inf"), n)),
            ("alarms", lambda n: self.prune_alarms(float("inf"), n)),
        ]
        for name, step in steps:
            for _ in range(MAX_BATCHES):
                if self._stop.is_set() or self.pruning.used_bytes() <= limit:
                    return
                n = step(self.config.batch_rows)
                setattr(out, name, getattr(out, name) + n)
                if n == 0:
                    break
                self._stop.wait(PAUSE_S)

    def _batches(self, step: Callable[[int], int]) -> int:
        total = 0
        for _ in range(MAX_BATCHES):
            if self._stop.is_set():
                break
            n = step(self.config.batch_rows)
            total += n
            if n < self.config.batch_rows:
                break
            self._stop.wait(PAUSE_S)
        return total

    def _release(self) -> int:
        """Free pages back to the file system, a step at a time; the pages handed back."""
        if self.in_memory:
            return 0
        if not self.pruning.incremental():
            if not self.idle() or self.pruning.used_bytes() > CONVERT_MAX_BYTES:
                return 0
            t0 = time.monotonic()
            self.pruning.make_incremental()
            log.warning("the job database was rewritten for incremental vacuum in %.1f s",
                        time.monotonic() - t0)
            return 0
        released = 0
        while not self._stop.is_set():
            n = self.pruning.release(RELEASE_PAGES)
            released += n
            if n < RELEASE_PAGES:
                break
            self._stop.wait(PAUSE_S)
        if released:
            self.pruning.checkpoint()
        return released
