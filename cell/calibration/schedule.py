"""Calibration checks on a schedule: every N production jobs or every M minutes, between jobs.

A PLC or MES can start a check itself (``POST /calibration/check``, OPC UA, Modbus); a cell
without one runs them here from ``[check] every_jobs`` / ``every_minutes``. A check starts
only when the arm has been idle for ``IDLE_S`` (no job holds the motion slot, none did in
that time), so it never interrupts a job and rarely meets the next one: a job asked for while
a check runs is refused ``busy`` as with any other job, and starts after it. Without a
recorded reference nothing is scheduled.
"""

from __future__ import annotations

import logging
import threading
import time

from cell.calibration.check import CHECK_KIND, CalibrationCheck
from cell.errors import CellError

log = logging.getLogger(__name__)

CALLER = "schedule"
IDLE_S = 2.0
POLL_S = 0.5
PRODUCTION_KINDS = ("approach", "track", "pick")


class CheckSchedule:
    def __init__(self, checks: CalibrationCheck) -> None:
        self.checks = checks
        self.core = checks.core
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None

    @property
    def enabled(self) -> bool:
        cc = self.core.config.check
        return cc.every_jobs > 0 or cc.every_minutes > 0

    def start(self) -> None:
        if self.enabled and self._thread is None:
            self._thread = threading.Thread(target=self._run, name="cell-check-schedule",
                                            daemon=True)
            self._thread.start()

    def close(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=5.0)

    def due(self, now_s: float) -> bool:
        """Whether a check is due: enough production jobs or minutes since the last check
        (or, without one, since the reference was recorded)."""
        reference = self.checks.store.get()
        if reference is None:
            return False
        jobs = self.core.jobs
        last = jobs.list_jobs(1, kind=CHECK_KIND)
        since = max(reference.recorded_at, last[0].created_at if last else 0.0)
        cc = self.core.config.check
        if cc.every_minutes > 0 and now_s - since >= 60.0 * cc.every_minutes:
            return True
        return cc.every_jobs > 0 and jobs.count_since(since, PRODUCTION_KINDS) >= cc.every_jobs

    def _run(self) -> None:
        slot = self.core.slot
        idle_since, generation = time.monotonic(), slot.generation
        while not self._stop.wait(POLL_S):
            if slot.current is not None or slot.generation != generation:
                idle_since, generation = time.monotonic(), slot.generation
                continue
            if time.monotonic() - idle_since < IDLE_S:
                continue
            try:
                if self.due(time.time()):
                    job = self.checks.check(CALLER)
                    log.info("scheduled calibration check started: job %s", job.id)
            except CellError as err:  # busy, arm not ready, camera lost: tried again later
                log.info("scheduled calibration check not started: %s", err.message)
            except Exception:
                log.exception("the calibration check schedule failed")
            idle_since, generation = time.monotonic(), slot.generation
