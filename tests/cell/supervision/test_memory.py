"""The native heap's housekeeping: bounded malloc arenas and a periodic malloc_trim."""

from __future__ import annotations

import pytest

from cell.supervision import memory
from tests.support.waiting import wait_until


def test_an_explicit_malloc_arena_max_is_left_to_glibc(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("MALLOC_ARENA_MAX", "4")
    assert memory.limit_arenas() is False


def test_the_trim_period_comes_from_the_environment(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.delenv("CELL_MALLOC_TRIM_S", raising=False)
    assert memory.trim_period_s() == memory.TRIM_PERIOD_S
    monkeypatch.setenv("CELL_MALLOC_TRIM_S", "0")
    assert memory.trim_period_s() == 0.0
    monkeypatch.setenv("CELL_MALLOC_TRIM_S", "soon")
    assert memory.trim_period_s() == memory.TRIM_PERIOD_S


@pytest.mark.skipif(memory._libc() is None, reason="not glibc")
def test_the_trimmer_trims_until_stopped() -> None:
    trimmer = memory.Trimmer(period_s=0.01)
    trimmer.start()
    try:
        wait_until(lambda: trimmer.trims >= 2, 5.0, "two trims")
    finally:
        trimmer.stop()
    n = trimmer.trims
    assert trimmer._thread is None and memory.trim() in (True, False)
    assert trimmer.trims == n
