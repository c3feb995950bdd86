"""The host watch: a failed job's message names the host when the host held the service still
before it failed, names the service itself when one of its own threads did, and says nothing
otherwise."""

from __future__ import annotations

import ctypes
import os
import subprocess
import sys
import time
from collections.abc import Callable
from pathlib import Path

import pytest

from cell.supervision.host_watch import (
    BLOCKED_STALL_MARK,
    HOST_STALL_MARK,
    OWN_STALL_MARK,
    STALL_S,
    WINDOW_S,
    HostWatch,
)
from estimator.transforms import pose_distance, translation_T
from tests.support.cell import running_cell, sim_config, tcp, world


def test_a_stall_before_a_failure_is_named_and_a_short_or_old_one_is_not() -> None:
    watch = HostWatch()
    now = 1000.0
    watch.woke(now - 3.0, 0.2)  # a short one
    assert watch.note(now - 20.0, now) is None
    watch.woke(now - WINDOW_S - 2.0, 1.5)  # long, but long before the failure
    assert watch.note(now - 20.0, now) is None
    watch.woke(now - 2.0, STALL_S + 0.3, cpu_s=0.05)  # the process hardly ran: the host
    note = watch.note(now - 20.0, now)
    assert note is not None and HOST_STALL_MARK in note and "0.80 s" in note, note
    assert watch.note(now - 1.0, now) is None  # it ended before the job began


def test_a_failure_seen_before_the_watch_woke_from_the_stall_still_names_it() -> None:
    # after a stall every thread wakes at once; the failing one may run before the watch
    watch = HostWatch()
    now = time.monotonic()
    watch._expect(now - 0.9, time.process_time(), 0)  # the watch's wake is 0.9 s overdue
    note = watch.note(now - 20.0, now)
    assert note is not None and HOST_STALL_MARK in note and "0.90 s" in note, note


def test_a_stall_the_service_ran_through_is_its_own() -> None:
    watch = HostWatch()
    now = 1000.0
    watch.woke(now - 2.0, STALL_S + 0.3, cpu_s=0.78)  # a thread of its own kept the others
    note = watch.note(now - 20.0, now)
    assert note is not None and OWN_STALL_MARK in note and HOST_STALL_MARK not in note, note
    watch.woke(now - 1.0, 0.3, cpu_s=0.0)
    watch.woke(now - 0.8, 0.2, cpu_s=0.0, switches=40)  # waited for the lock all along
    watch.woke(now - 0.5, 0.05, cpu_s=0.0)  # on time enough: not a stall
    assert watch.counts == {"host": 1, "own": 1, "blocked": 1}  # what /metrics exports
    assert watch.seconds["own"] == STALL_S + 0.3 and watch.seconds["host"] == 0.3


def _hold_the_interpreter(seconds: float) -> None:
    """Keep every other thread of this process from running for ``seconds``: a busy loop
    that does not hand the interpreter over (what a starved host does to the service)."""
    interval = sys.getswitchinterval()
    sys.setswitchinterval(seconds + 1.0)
    try:
        end = time.monotonic() + seconds
        while time.monotonic() < end:
            pass
    finally:
        sys.setswitchinterval(interval)


def _stop_this_process(seconds: float) -> None:
    """SIGSTOP this whole process for ``seconds`` from outside, as a host that does not
    schedule it does (a shell sends the STOP and, later, the CONT)."""
    subprocess.Popen(["sh", "-c", f"kill -STOP {os.getpid()}; sleep {seconds}; "
                      f"kill -CONT {os.getpid()}"]).wait()
    time.sleep(0.05)  # the CONT has come: this line runs after it


def _block_holding_the_interpreter(seconds: float) -> None:
    """Block in a C call that keeps the interpreter's lock (libc's usleep through
    ``ctypes.PyDLL``): every other thread stands still, and no CPU is used."""
    ctypes.PyDLL(None).usleep(int(seconds * 1e6))


@pytest.mark.parametrize(("hold", "mark", "not_mark"), [
    (_stop_this_process, HOST_STALL_MARK, OWN_STALL_MARK),
    (_hold_the_interpreter, OWN_STALL_MARK, HOST_STALL_MARK),
    (_block_holding_the_interpreter, BLOCKED_STALL_MARK, HOST_STALL_MARK),
], ids=["host", "own", "blocked"])
def test_an_approach_that_fails_after_the_service_was_held_still_names_who_held_it(
        tmp_path: Path, hold: Callable[[float], None], mark: str, not_mark: str) -> None:
    with running_cell(sim_config(tmp_path)) as cell:
        world(cell).set_target(translation_T(60.0, 40.0, 0.0) @ world(cell).true_T_base_target())
        job = cell.approach("test", speed_mm_s=30.0)
        start = tcp(cell)
        deadline = time.monotonic() + 5.0
        while pose_distance(tcp(cell), start)[0] < 2.0:
            assert time.monotonic() < deadline, "the approach never started moving"
            time.sleep(0.01)
        hold(0.8)
        world(cell).set_camera_lost(True)
        deadline = time.monotonic() + 5.0
        while not cell.job(job.id).finished:
            assert time.monotonic() < deadline, "the approach did not end"
            time.sleep(0.01)
        ended = cell.job(job.id)
        # the stall itself may fail it first (the arm's stream seen stale on waking)
        assert ended.state == "failed" and ended.error_code in (
            "camera_lost", "arm_disconnected", "target_lost"), ended
        message = ended.error_message or ""
        if mark == HOST_STALL_MARK:  # a stopped process: not a computation of the service,
            # though its threads' wakes around the stop may read as a wait for the lock
            assert (mark in message or BLOCKED_STALL_MARK in message) \
                and OWN_STALL_MARK not in message, message
        else:
            assert mark in message and not_mark not in message, message
        world(cell).set_camera_lost(False)


def test_a_stall_of_seconds_leaves_every_threads_stack(tmp_path: Path) -> None:
    # in a process of its own: one armed dump per process, and pytest's is left alone
    path = tmp_path / "stall-traces.txt"
    script = f"""
import ctypes, time
from pathlib import Path
from cell.supervision.host_watch import HostWatch
from cell.supervision.stall_traces import StallTraces

def block_while_holding_the_interpreter():
    ctypes.PyDLL(None).usleep(4_500_000)

watch = HostWatch(traces=StallTraces(Path({str(path)!r})))
watch.start()
time.sleep(1.5)  # armed
block_while_holding_the_interpreter()
time.sleep(0.3)  # the watch wakes and says how long it was
watch.close()
print(watch.counts)
"""
    out = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True,
                         timeout=60, check=True).stdout
    assert "'blocked': 1" in out, out  # blocked holding the lock, not computing
    text = path.read_text()
    assert "Timeout" in text and "block_while_holding_the_interpreter" in text, text
    assert "-- stall of 4." in text or "-- stall of 5." in text, text
