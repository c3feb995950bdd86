"""Linux timer slack for threads that poll: fewer wake-ups for the same work.

ur_rtde's receive threads do not block on their socket: between packages they sleep 100 us and
look again, some 10 000 wake-ups a second per client whatever the RTDE rate. Measured on the
2-core machine, a receive client at 125 Hz and a control client at 500 Hz cost 19.5 % of a core
this way while the arm stood still. A thread's timer slack lets the kernel fire its short
sleeps up to that much later, grouped with other wake-ups; threads inherit it from the thread
that creates them. With 1 ms the same two clients cost 4.9 %, with 2 ms 3.1 %, and a package
is read at most that much later (the control client's packages come every 2 ms, so they never
pile up).

Elsewhere than on Linux this does nothing.
"""

from __future__ import annotations

import contextlib
import ctypes
import sys
from collections.abc import Iterator

_PR_SET_TIMERSLACK = 29
_PR_GET_TIMERSLACK = 30


def _prctl(option: int, value: int) -> int:
    if not sys.platform.startswith("linux"):
        return -1
    libc = ctypes.CDLL(None, use_errno=True)
    return int(libc.prctl(option, ctypes.c_ulong(value), 0, 0, 0))


def set_timer_slack(slack_s: float) -> bool:
    """Set the calling thread's timer slack; False where that is not possible."""
    return _prctl(_PR_SET_TIMERSLACK, max(1, round(slack_s * 1e9))) == 0


def timer_slack_s() -> float | None:
    """The calling thread's timer slack; None where it cannot be read."""
    ns = _prctl(_PR_GET_TIMERSLACK, 0)
    return ns / 1e9 if ns > 0 else None


@contextlib.contextmanager
def timer_slack(slack_s: float) -> Iterator[None]:
    """The calling thread's timer slack set for the block (threads started in it keep it)."""
    before = _prctl(_PR_GET_TIMERSLACK, 0)
    set_timer_slack(slack_s)
    try:
        yield
    finally:
        if before > 0:
            _prctl(_PR_SET_TIMERSLACK, before)
