"""Summary statistics a closed loop reports about its timing and its gain."""

from __future__ import annotations

from cell.results.base import Result


class LatencyStats(Result):
    """Milliseconds over a run's samples (pose intervals, frame-to-filter latency)."""

    median: float
    p95: float
    max: float


class Percentiles(Result):
    """The 5th, 50th and 95th percentile of a run's samples."""

    p5: float
    median: float
    p95: float
