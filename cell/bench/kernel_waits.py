"""Which of a process's threads wait in the kernel, sampled from outside it.

A stall the service's host watch calls *blocked* (a thread held the interpreter and did not
run) is the service's own defect when that thread sat in a call that does not release the
interpreter, and the host's when it waited in the kernel for something the host did not run:
a memory-map lock held by a starved kernel thread, a tty's work item. Only an observer outside
the stalled process can tell, while the stall lasts: this one reads the state of each thread
(``/proc/PID/task/TID/stat``) every ``period_s`` and, for a thread in uninterruptible sleep
(``D``), the kernel function it waits in (``wchan``).
"""

from __future__ import annotations

import os
import threading
import time
from collections import Counter
from dataclasses import dataclass
from pathlib import Path

PERIOD_S = 0.1
KEEP_SAMPLES = 200_000  # ~5.5 h at 0.1 s; only samples with a thread in D are kept


@dataclass(frozen=True)
class WaitShare:
    """Over a time window: the share of samples with a thread in D, and where they waited."""

    share: float
    samples: int
    wchans: dict[str, int]


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
        out.append(wchan if wchan and wchan != "0" else "?")
    return out


class KernelWaits:
    """Samples ``pid``'s threads in a daemon thread from :meth:`start` to :meth:`stop`."""

    def __init__(self, pid: int, period_s: float = PERIOD_S) -> None:
        self.pid = pid
        self.period_s = period_s
        self._lock = threading.Lock()
        self._times: list[float] = []  # every sample's time (monotonic s)
        self._waits: dict[float, list[str]] = {}  # the samples with a thread in D
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

    def _run(self) -> None:
        while not self._stop.wait(self.period_s):
            now = time.monotonic()
            waits = threads_in_d(self.pid)
            with self._lock:
                if len(self._times) >= KEEP_SAMPLES:
                    gone = self._times[: KEEP_SAMPLES // 10]
                    del self._times[: KEEP_SAMPLES // 10]
                    for t in gone:
                        self._waits.pop(t, None)
                self._times.append(now)
                if waits:
                    self._waits[now] = waits

    def share(self, t0_s: float, t1_s: float) -> WaitShare:
        """Samples between ``t0_s`` and ``t1_s`` (monotonic): how many had a thread in D."""
        with self._lock:
            inside = [t for t in self._times if t0_s <= t <= t1_s]
            waited = [self._waits[t] for t in inside if t in self._waits]
        wchans: Counter[str] = Counter(w for ws in waited for w in set(ws))
        return WaitShare(len(waited) / len(inside) if inside else 0.0, len(inside),
                         dict(wchans.most_common(5)))
