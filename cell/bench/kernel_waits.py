"""Which of a process's threads wait in the kernel, sampled from outside it.

A stall the service's host watch calls *blocked* (a thread held the interpreter and did not
run) is the service's own defect when that thread sat in a call that does not release the
interpreter, and the host's when it waited in the kernel for something the host did not run:
a memory-map lock held by a starved kernel thread, a tty's work item. Only an observer outside
the stalled process can tell, while the stall lasts: this one reads the state of each thread
(``/proc/PID/task/TID/stat``) every ``period_s`` and, for a thread in uninterruptible sleep
(``D``), the kernel function it waits in (``wchan``). Any thread in D counts: the sampler
cannot see which one holds the interpreter's lock.
"""

from __future__ import annotations

import bisect
import os
import sys
import threading
import time
from collections import Counter
from dataclasses import dataclass
from pathlib import Path

PERIOD_S = 0.1
MAX_GAP_S = 0.5  # samples further apart than this (the sampler starved) end a run
KEEP_S = 3600.0 * 6  # samples older than this are dropped (a failure is judged at once)


@dataclass(frozen=True)
class WaitRun:
    """The longest stretch of samples, each with a thread of the process in D."""

    duration_s: float
    samples: int
    wchans: dict[str, int]  # the kernel functions waited in: in how many of its samples


def threads_in_d(pid: int) -> list[str]:
    """The kernel functions the threads of ``pid`` in state D wait in ("?" when hidden)."""
    out: list[str] = []
    try:
        tids = os.listdir(f"/proc/{pid}/task")
    except OSError:
        return out
    for tid in tids:
        base = Path(f"/proc/{pid}/task/{tid}")
        try:
            stat = (base / "stat").read_text()
        except OSError:
            continue
        if stat[stat.rindex(")") + 2] != "D":
            continue
        try:
            wchan = (base / "wchan").read_text().strip()
        except OSError:
            wchan = ""
        out.append(sys.intern(wchan) if wchan and wchan != "0" else "?")
    return out


class KernelWaits:
    """Samples ``pid``'s threads in a daemon thread from :meth:`start` to :meth:`stop` (or
    over a ``with`` block)."""

    def __init__(self, pid: int, period_s: float = PERIOD_S) -> None:
        self.pid = pid
        self.period_s = period_s
        self._lock = threading.Lock()
        self._times: list[float] = []  # every sample's time (monotonic s), ascending
        self._in_d: list[tuple[str, ...]] = []  # each sample's threads in D (mostly empty)
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None

    def start(self) -> KernelWaits:
        self._thread = threading.Thread(target=self._run, name="kernel-waits", daemon=True)
        self._thread.start()
        return self

    def stop(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=2.0)

    def __enter__(self) -> KernelWaits:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()

    def _run(self) -> None:
        while not self._stop.wait(self.period_s):
            self.add(time.monotonic(), threads_in_d(self.pid))

    def add(self, t_s: float, in_d: list[str]) -> None:
        """One sample: at ``t_s`` (monotonic, ascending) these threads were in D."""
        with self._lock:
            if self._times and self._times[0] < t_s - KEEP_S:
                cut = bisect.bisect_left(self._times, t_s - KEEP_S)
                del self._times[:cut], self._in_d[:cut]
            self._times.append(t_s)
            self._in_d.append(tuple(in_d))

    def longest_run(self, t0_s: float, t1_s: float) -> WaitRun:
        """Between ``t0_s`` and ``t1_s``: the longest stretch of consecutive samples (none
        more than ``MAX_GAP_S`` apart) in each of which a thread was in D."""
        with self._lock:
            lo = bisect.bisect_left(self._times, t0_s)
            hi = bisect.bisect_right(self._times, t1_s)
            times, in_d = self._times[lo:hi], self._in_d[lo:hi]
        best: tuple[int, int] | None = None  # [first, last + 1) of the longest run
        i = 0
        while i < len(times):
            if not in_d[i]:
                i += 1
                continue
            j = i
            while (j + 1 < len(times) and in_d[j + 1]
                   and times[j + 1] - times[j] <= MAX_GAP_S):
                j += 1
            if best is None or times[j] - times[i] > times[best[1] - 1] - times[best[0]]:
                best = (i, j + 1)
            i = j + 1
        if best is None:
            return WaitRun(0.0, 0, {})
        run = range(*best)
        wchans: Counter[str] = Counter(w for j in run for w in set(in_d[j]))
        return WaitRun(times[best[1] - 1] - times[best[0]] + self.period_s, len(run),
                       dict(wchans.most_common(5)))
