"""Whether the cell can still write what it keeps: the job database and the disk under it.

A background thread looks every ``CHECK_PERIOD_S``: the job store's tiny write probe (one row
rewritten, and only when nothing else wrote meanwhile; a failed real write is seen at once,
the store remembers it) and the free space of each file system the service writes to (the
job database's directory, the calibration and image log directories). ``/health`` reads the
newest outcome (:meth:`StorageWatch.reasons`) from the cell's snapshot: nothing here runs on a
reader's path, and nothing scans the database.

While a job runs the probe looks every ``JOB_CHECK_PERIOD_S``: a disk that fails mid-job is
seen within that, and :func:`stop_unrecordable_jobs` stops the job (``storage_failed``, the
arm commanded to stop): a cell whose record cannot be written does not go on producing. The
job's end reaches every interface from memory (:mod:`cell.jobs.unsaved`).
"""

from __future__ import annotations

import logging
import os
import shutil
import threading
import time
from collections.abc import Callable
from pathlib import Path

from cell.error_codes import ErrorCode
from cell.errors import UnavailableError
from cell.jobs import JobStore
from cell.motion.guard import MotionSlot

log = logging.getLogger(__name__)
CHECK_PERIOD_S = 2.0
JOB_CHECK_PERIOD_S = 0.25
# A file system the service writes to is "near full" below either of these: the job and audit
# log, taught poses and the image log of failed locates must keep fitting, and a log that
# fails to write is lost exactly when it is needed.
DISK_MIN_FREE_BYTES = 500 * 1024 * 1024
DISK_MIN_FREE_FRACTION = 0.05

Reason = dict[str, str]


def _mb(n: float) -> str:
    return f"{n / (1024 * 1024):.0f} MB"


def disk_reason(path: Path) -> Reason | None:
    """``disk_space`` when the file system holding ``path`` is near full, else None."""
    usage = shutil.disk_usage(path)
    fraction = usage.free / usage.total if usage.total else 1.0
    if usage.free >= DISK_MIN_FREE_BYTES and fraction >= DISK_MIN_FREE_FRACTION:
        return None
    return {"code": "disk_space",
            "message": f"the file system of {path} is nearly full: {_mb(usage.free)} free of "
                       f"{_mb(usage.total)} ({fraction:.1%}); below {_mb(DISK_MIN_FREE_BYTES)} "
                       f"or {DISK_MIN_FREE_FRACTION:.0%} the job log may stop being written"}


class StorageWatch:
    """The job store's writability and the free disk space, checked in the background."""

    def __init__(self, jobs: JobStore, dirs: list[Path],
                 busy: Callable[[], bool] = lambda: False) -> None:
        self.jobs = jobs
        self.dirs = dirs
        self.busy = busy  # whether a job runs: the probe then looks more often
        self._disk: list[Reason] = []
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None

    def start(self) -> None:
        self.check()
        self._thread = threading.Thread(target=self._loop, name="cell-storage", daemon=True)
        self._thread.start()

    def close(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=5.0)

    def reasons(self) -> list[Reason]:
        """Why storage makes the cell degraded (empty: it does not); never waits."""
        out = list(self._disk)
        error = self.jobs.write_error
        if error is not None:
            out.insert(0, {"code": "storage", "message": "the job database cannot be written "
                           f"({self.jobs.path}): {error}; new jobs are refused and job ends "
                           f"are kept in memory ({self.jobs.unsaved} waiting)"})
        return out

    def check(self) -> None:
        """One look at the store and the disks (the background thread's, and at start)."""
        self.jobs.probe(idle_s=CHECK_PERIOD_S)
        self.check_disks()

    def check_disks(self) -> None:
        disk: list[Reason] = []
        seen: set[int] = set()
        for d in self.dirs:
            try:
                device = os.stat(d).st_dev
                if device in seen:
                    continue
                seen.add(device)
                reason = disk_reason(d)
            except OSError as err:
                log.debug("no disk usage for %s: %s", d, err)
                continue
            if reason is not None:
                disk.append(reason)
        self._disk = disk

    def _loop(self) -> None:
        disks_s = time.monotonic()
        while not self._stop.wait(JOB_CHECK_PERIOD_S if self.busy() else CHECK_PERIOD_S):
            try:
                if self.busy():
                    self.jobs.probe(idle_s=JOB_CHECK_PERIOD_S)
                else:
                    self.jobs.probe(idle_s=CHECK_PERIOD_S)
                if time.monotonic() - disks_s >= CHECK_PERIOD_S:
                    disks_s = time.monotonic()
                    self.check_disks()
            except Exception:  # the watch must outlive any one bad look
                log.exception("storage check failed")


def stop_unrecordable_jobs(jobs: JobStore, slot: MotionSlot,
                           stop: Callable[[str, str], object]) -> None:
    """When a write to ``jobs`` fails, the job holding ``slot`` ends ``storage_failed`` and
    ``stop(caller, reason)`` stops the arm (the job's end then comes from memory)."""

    def failed(error: str) -> None:
        motion = slot.current
        if motion is None or motion.job_id is None:
            return
        slot.cancel(UnavailableError(
            ErrorCode.storage_failed, f"the job database cannot be written ({error}): the "
            "job was stopped, its record is kept in memory until the disk takes writes again"))
        stop("service", "storage_failed")

    jobs.on_write_failed(failed)


def state_dirs(jobs: JobStore, *others: str) -> list[Path]:
    """The directories the service writes to: the job database's and ``others`` (one that
    does not exist yet is skipped until it does)."""
    candidates = [] if str(jobs.path) == ":memory:" else [jobs.path.parent]
    return candidates + [Path(o) for o in others if o]
