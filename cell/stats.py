"""Counters the cell keeps for ``/metrics``; thread-safe.

Beside the counts, what finished jobs said about the calibration between checks: an approach
(or a pick's) that saw a target at rest from several arm poses reports how far the target
seemed to move while the arm moved (``consistency.motion``: zero with a true calibration), and
a calibration check reports its change at the tool. The newest of each is kept for the
``cell_calibration_*`` gauges, so a drift shows on a dashboard before the next check.
"""

from __future__ import annotations

import threading
from collections import Counter
from dataclasses import dataclass

from cell.results.approach import ApproachBase
from cell.results.check import CheckResult
from cell.results.jobs import JobResult
from cell.results.pick import PickResult


@dataclass(frozen=True)
class CalibrationEvidence:
    """The newest judged disagreement (mm, deg) and check (mm, deg, drifted), None before
    any; ``inconsistent``: jobs whose evidence disagreed past its limits."""

    disagreement_mm: float | None = None
    disagreement_deg: float | None = None
    check_tcp_error_mm: float | None = None
    check_tcp_error_deg: float | None = None
    check_drifted: bool | None = None
    inconsistent: int = 0


class CellStats:
    def __init__(self) -> None:
        self._lock = threading.Lock()
        self.jobs: Counter[str] = Counter()  # final state -> count
        self.refusals: Counter[str] = Counter()  # code -> count
        self.deadman_stops = 0
        self.stops = 0
        self.reconnects: Counter[str] = Counter()  # device -> successful reconnects
        self.calibration = CalibrationEvidence()

    def count_job_end(self, state: str) -> None:
        with self._lock:
            self.jobs[state] += 1

    def observe_result(self, result: JobResult | None) -> None:
        """Keep what a succeeded job's result says about the calibration."""
        if isinstance(result, PickResult):
            result = result.approach
        c = self.calibration
        if isinstance(result, ApproachBase):
            motion = result.consistency.motion
            if motion.judged and motion.max_target_moved_mm is not None:
                c = CalibrationEvidence(motion.max_target_moved_mm, motion.max_target_moved_deg,
                                        c.check_tcp_error_mm, c.check_tcp_error_deg,
                                        c.check_drifted, c.inconsistent
                                        + (result.consistency.verdict == "inconsistent"))
        elif isinstance(result, CheckResult):
            c = CalibrationEvidence(c.disagreement_mm, c.disagreement_deg, result.tcp_error_mm,
                                    result.tcp_error_deg, result.verdict == "drifted",
                                    c.inconsistent)
        with self._lock:
            self.calibration = c

    def count_refusal(self, code: str) -> None:
        with self._lock:
            self.refusals[code] += 1

    def count_stop(self) -> None:
        with self._lock:
            self.stops += 1

    def count_deadman_stop(self) -> None:
        with self._lock:
            self.deadman_stops += 1

    def count_reconnect(self, device: str) -> None:
        with self._lock:
            self.reconnects[device] += 1
