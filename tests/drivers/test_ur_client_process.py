"""The ur_rtde child's parent side: a child that is replaced leaves nothing open behind."""

from __future__ import annotations

import contextlib
import os
import signal
import time

import pytest

from drivers.ur.client_process import Call, ClientDied, ClientProcess, _write_within
from tests.support.waiting import wait_until


def _fds() -> int:
    return len(os.listdir("/proc/self/fd"))


def test_children_killed_or_closed_leave_no_descriptors() -> None:
    """A cell replaces its child after every lost link (about 20 an hour in a soak); a
    replaced child whose two pipes stayed open would leave the service without descriptors."""
    ClientProcess("127.0.0.1").kill("warm up")  # the first child loads what stays loaded
    before = _fds()
    # held, as a callback or a late reply can hold a replaced child: its pipes must be closed
    # by the end itself, not by the garbage collector some time later
    children = [ClientProcess("127.0.0.1") for _ in range(10)]
    for k, child in enumerate(children):
        if k % 2:
            child.kill("replaced")
        else:
            child.close()
    wait_until(lambda: _fds() <= before, 10.0,
               f"the descriptors back to {before} (now {_fds()})")
    assert all(c.dead_reason is not None for c in children)


def test_a_write_nobody_takes_ends_at_its_deadline() -> None:
    r, w = os.pipe()
    try:
        os.set_blocking(w, False)
        t0 = time.monotonic()
        with pytest.raises(TimeoutError):
            _write_within(w, b"x" * 300_000, time.monotonic() + 0.2)  # the pipe holds 64 KB
        assert time.monotonic() - t0 < 2.0
    finally:
        os.close(r)
        os.close(w)


def test_a_child_that_stopped_reading_fails_a_request_within_its_timeout() -> None:
    """A frozen child does not read its requests; once its pipe is full a blocking write
    would hold the request (and every later one, a stop's too) for as long as it stays
    frozen. The request fails by its timeout instead, and the child is killed."""
    child = ClientProcess("127.0.0.1")
    try:
        os.kill(child._proc.pid, signal.SIGSTOP)
        t0 = time.monotonic()
        with pytest.raises(ClientDied, match=r"did not take the request|took no request"):
            child.request(Call("dash", "noop", (b"x" * 300_000,)), timeout_s=1.0)
        assert time.monotonic() - t0 < 4.0, "the request waited on the frozen child"
        assert child.dead_reason is not None
        wait_until(lambda: child._proc.poll() is not None, 10.0, "the frozen child killed")
    finally:
        with contextlib.suppress(ProcessLookupError):
            os.kill(child._proc.pid, signal.SIGCONT)
        child.kill("test over")
