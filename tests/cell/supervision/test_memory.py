"""The native heap's housekeeping: bounded malloc arenas and a periodic malloc_trim; and the
library pages kept in RAM once used."""

from __future__ import annotations

import os
import resource
import subprocess
import sys

import pytest

from cell.supervision import memory
from tests.support.waiting import wait_until


def test_an_explicit_malloc_arena_max_is_left_to_glibc(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("MALLOC_ARENA_MAX", "4")
    assert memory.limit_arenas() is False


def test_the_heap_is_kept_unless_the_environment_says_otherwise(
        monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("MALLOC_TRIM_THRESHOLD_", "131072")  # a glibc tunable: glibc decides
    assert memory.keep_heap() is False
    monkeypatch.delenv("MALLOC_TRIM_THRESHOLD_")
    monkeypatch.setenv("CELL_MALLOC_KEEP", "0")
    assert memory.keep_heap() is False
    monkeypatch.delenv("CELL_MALLOC_KEEP")
    # in a child, so this test process keeps glibc's defaults: the thresholds are accepted
    code = "from cell.supervision import memory; raise SystemExit(0 if memory.keep_heap() else 1)"
    assert subprocess.run([sys.executable, "-c", code], env=os.environ.copy()).returncode == 0


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


_LOCK_SCRIPT = """
import numpy
from cell.supervision.memory import lock_file_pages
covered, why = lock_file_pages()
status = dict(line.split(":", 1) for line in open("/proc/self/status"))
print(covered, int(status["VmLck"].split()[0]) * 1024, int(status["VmRSS"].split()[0]) * 1024,
      why)
"""


def _locked(env: dict[str, str]) -> tuple[int, int, int, str]:
    out = subprocess.run([sys.executable, "-c", _LOCK_SCRIPT], capture_output=True, text=True,
                         timeout=60, check=True, env={**os.environ, **env}).stdout.split()
    return int(out[0]), int(out[1]), int(out[2]), " ".join(out[3:])


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="mlock2 and /proc are Linux's")
def test_library_pages_are_locked_once_touched_without_reading_them_all_in() -> None:
    soft, _ = resource.getrlimit(resource.RLIMIT_MEMLOCK)
    if os.geteuid() != 0 and soft != resource.RLIM_INFINITY:
        pytest.skip("RLIMIT_MEMLOCK is bounded here (the systemd unit lifts it)")
    covered, locked, rss, why = _locked({})
    assert why == "None" and covered > 50e6, (covered, why)  # numpy and the interpreter
    assert locked >= covered  # the kernel counts the whole ranges...
    assert rss < covered  # ...but only what was touched is in RAM (MLOCK_ONFAULT)


def test_the_lock_can_be_turned_off() -> None:
    covered, locked, _, why = _locked({"CELL_LOCK_FILE_PAGES": "0"})
    assert (covered, locked) == (0, 0) and "off" in why, why
