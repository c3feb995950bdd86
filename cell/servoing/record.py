"""What a loop records for its result: frame counts and timings, and the error history."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

HISTORY_POINTS = 100  # the error history in a job's result is downsampled to this


@dataclass
class FrameStats:
    frames: int = 0  # measurements taken
    failed: int = 0  # frames that did not show the target (or gave no measurement)
    stale: int = 0  # too old once estimated (``limits.max_pose_age_s``): never used
    lags: list[float] = field(default_factory=list)  # mid-exposure to taken (s)
    gaps: list[float] = field(default_factory=list)  # between measurements (s)
    last_s: float = 0.0  # when the last was taken (the first gap counts from the start)

    def taken(self, now_s: float, exposure_s: float) -> None:
        self.gaps.append(now_s - self.last_s)
        self.lags.append(now_s - exposure_s)
        self.last_s = now_s
        self.frames += 1


def ms_stats(xs: list[float]) -> dict[str, float] | None:
    if not xs:
        return None
    a = np.asarray(xs) * 1000.0
    return {"median": round(float(np.median(a)), 1), "p95": round(float(np.percentile(a, 95)), 1),
            "max": round(float(a.max()), 1)}


class History:
    """The errors at each new measurement, ``t_s`` from the loop's start."""

    def __init__(self) -> None:
        self.rows: list[dict[str, float]] = []

    def add(self, t_s: float, errors: dict[str, float]) -> None:
        self.rows.append({"t_s": t_s} | errors)

    def downsampled(self, n: int = HISTORY_POINTS, last: int | None = None
                    ) -> list[dict[str, float]]:
        """At most ``n`` rows (of the ``last`` ones), evenly spread, rounded to 4 decimals."""
        rows = self.rows if last is None else self.rows[-last:]
        if len(rows) > n:
            idx = np.unique(np.linspace(0, len(rows) - 1, n).round().astype(int))
            rows = [rows[i] for i in idx]
        return [{k: round(v, 4) for k, v in row.items()} for row in rows]
