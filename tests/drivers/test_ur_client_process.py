"""The ur_rtde child's parent side: a child that is replaced leaves nothing open behind."""

from __future__ import annotations

import os

from drivers.ur.client_process import ClientProcess
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
