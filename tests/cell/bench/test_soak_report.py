"""The soak bench's growth figures: a least-squares slope per hour, after the warm-up."""

from __future__ import annotations

from cell.bench.soak import slope_per_h


def test_the_slope_is_per_hour_and_skips_the_warm_up() -> None:
    t = [60.0 * i for i in range(11)]  # ten minutes
    rss = [400.0 + (50.0 if i == 0 else 0.0) + 1.0 * i for i in range(11)]  # +1 MB/min
    assert slope_per_h(t, rss, skip=0.1) == 60.0  # the first sample's spike is left out
    assert slope_per_h(t, [5.0] * 11) == 0.0
    assert slope_per_h(t[:2], rss[:2]) is None  # too few samples to fit a line
    assert slope_per_h([], []) is None
