"""ControllerClock: pose-history stamps on the controller's clock, not when a sample was seen."""

from __future__ import annotations

import numpy as np
import pytest

from drivers.pose_history import ControllerClock


def test_stamps_follow_the_controller_clock_through_reader_jitter() -> None:
    """Samples every 8 ms, seen 1 ms (transport) plus 0-4 ms (a polling reader) later: the
    stamps are the controller's instants plus the smallest delay, so their error is the
    transport floor, not the poll jitter."""
    rng = np.random.default_rng(0)
    clock = ControllerClock(window_s=2.0)
    offset = 1000.0  # host monotonic = controller uptime + 1000 s
    errors = []
    for k in range(500):
        c = k * 0.008
        seen = offset + c + 0.001 + rng.uniform(0.0, 0.004)
        stamp = clock.host_time(c, seen)
        assert stamp <= seen
        if k > 50:
            errors.append(stamp - (offset + c))
    assert max(errors) < 0.0012  # at most the transport floor (1 ms) plus a sliver
    assert min(errors) > 0.0009
    seen_errors = 0.001 + 0.002  # what stamping on arrival gives on average
    assert float(np.mean(errors)) < seen_errors / 2


def test_a_restarted_controller_starts_over() -> None:
    clock = ControllerClock()
    for k in range(100):
        clock.host_time(50.0 + k * 0.008, 1000.0 + k * 0.008 + 0.001)
    # the controller restarts: its uptime begins again near zero, the host clock goes on
    stamp = clock.host_time(0.1, 1010.0)
    assert stamp == pytest.approx(1010.0)
    assert clock.host_time(0.108, 1010.009) == pytest.approx(1010.008)


def test_the_offset_follows_drift_within_the_window() -> None:
    """An old, smaller offset leaves the window: the newer, larger delay floor takes over."""
    clock = ControllerClock(window_s=1.0)
    for k in range(200):  # 1.6 s with 1 ms delay
        clock.host_time(k * 0.008, 100.0 + k * 0.008 + 0.001)
    for k in range(200, 600):  # then 3 ms delay (the host's clock drifted by 2 ms)
        stamp = clock.host_time(k * 0.008, 100.0 + k * 0.008 + 0.003)
    assert stamp == pytest.approx(100.0 + 599 * 0.008 + 0.003)
