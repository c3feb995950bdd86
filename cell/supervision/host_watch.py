"""Is the host letting this service run? A thread that asks to wake every ``PERIOD_S`` and
notes how late it woke.

On an overloaded host (CPU-bound neighbours, a virtual machine whose CPUs the hypervisor
takes away) every thread of the service can stand still for a second or more: the ur_rtde
child's samples are not read (``no RTDE data``), no frame is examined (``target_lost``), a
move's end is seen too late (``motion_failed``), the gripper's answer misses its timeout.
Each of those failures then names the device it waited on, which sends the operator to the
wrong place. The watch keeps the wakes later than ``NOTE_S`` for ``KEEP_S``; a failed job's
message says when the host held the service still for ``STALL_S`` or more in the
``WINDOW_S`` before it failed (:meth:`HostWatch.note`), so the cause names the host.

A late wake measures what every Python thread here waits for: the CPU and the interpreter's
lock. It costs a wake every 20 ms (well under 1 % of a core).
"""

from __future__ import annotations

import threading
import time
from collections import deque

PERIOD_S = 0.02
NOTE_S = 0.1  # a wake this late is kept
STALL_S = 0.5  # a failure with a stall this long before it names the host
WINDOW_S = 10.0  # how far before a failure a stall is looked for
KEEP_S = 600.0
HOST_STALL_MARK = "the host did not let this service run"  # in a failed job's message


class HostWatch:
    def __init__(self, period_s: float = PERIOD_S) -> None:
        self.period_s = period_s
        self._late: deque[tuple[float, float]] = deque()  # (woke at, how late), oldest first
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None

    def start(self) -> None:
        self._thread = threading.Thread(target=self._run, name="host-watch", daemon=True)
        self._thread.start()

    def close(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=2.0)

    def _run(self) -> None:
        due = time.monotonic() + self.period_s
        while not self._stop.wait(max(0.0, due - time.monotonic())):
            now = time.monotonic()
            self.woke(now, now - due)
            due = now + self.period_s

    def woke(self, now_s: float, late_s: float) -> None:
        """One wake, ``late_s`` after it was due (the watch's thread; tests feed it)."""
        if late_s < NOTE_S:
            return
        with self._lock:
            self._late.append((now_s, late_s))
            while self._late and self._late[0][0] < now_s - KEEP_S:
                self._late.popleft()

    def worst_s(self, since_s: float, until_s: float | None = None) -> tuple[float, float]:
        """The longest stall that overlapped ``[since_s, until_s]`` (monotonic s) and when
        it ended, ``(0, 0)`` when none was noted."""
        until = time.monotonic() if until_s is None else until_s
        with self._lock:
            overlapping = [(late, at) for at, late in self._late
                           if at >= since_s and at - late <= until]
        return max(overlapping, default=(0.0, 0.0))

    def note(self, since_s: float, now_s: float | None = None) -> str | None:
        """A sentence for a failure at ``now_s`` when the host held the service still for
        ``STALL_S`` or more since ``since_s`` (at most ``WINDOW_S`` back), else None."""
        now = time.monotonic() if now_s is None else now_s
        late, at = self.worst_s(max(since_s, now - WINDOW_S), now)
        if late < STALL_S:
            return None
        return (f"{HOST_STALL_MARK} for {late:.2f} s, {now - at:.1f} s before this failure: "
                "the host is overloaded (CPU-bound neighbours, or a virtual machine's CPUs "
                "taken away)")
