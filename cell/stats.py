"""Counters the cell keeps for ``/metrics``; thread-safe."""

from __future__ import annotations

import threading
from collections import Counter


class CellStats:
    def __init__(self) -> None:
        self._lock = threading.Lock()
        self.jobs: Counter[str] = Counter()  # final state -> count
        self.refusals: Counter[str] = Counter()  # code -> count
        self.deadman_stops = 0
        self.stops = 0
        self.reconnects: Counter[str] = Counter()  # device -> successful reconnects

    def count_job_end(self, state: str) -> None:
        with self._lock:
            self.jobs[state] += 1

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
