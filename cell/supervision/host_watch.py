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
lock. Two counts over the late interval tell them apart:

- the service's CPU time: one that ran all along kept its own threads waiting (``own``: a
  long computation holding the interpreter, the service's defect);
- the watch thread's voluntary context switches (Linux, ``/proc/thread-self/status``): a
  thread waiting for the interpreter's lock wakes every switch interval (5 ms) to ask for it,
  hundreds of times a second; a thread the host does not run (its CPUs busy, the process
  stopped, the virtual machine paused) switches not at all (``host``). Many switches and
  little CPU (``blocked``): one of the service's threads was blocked while it held the lock,
  either in a call that does not hand it over (the service's defect) or in the kernel, on a
  page read back from disk or kernel work the host starved (the host's). The stacks in
  ``stall-traces.txt`` (:mod:`cell.supervision.stall_traces`) say which.

The failed job's message says which of the three. It costs a wake and a small read every
20 ms (well under 1 % of a core).
"""

from __future__ import annotations

import threading
import time
from collections import deque
from dataclasses import dataclass

from cell.supervision.stall_traces import StallTraces

PERIOD_S = 0.02
NOTE_S = 0.1  # a wake this late is kept
STALL_S = 0.5  # a failure with a stall this long before it is explained by it
WINDOW_S = 10.0  # how far before a failure a stall is looked for
KEEP_S = 600.0
# The service ran for at least this share of a stall: its own doing. A process the host does
# not schedule (stopped, its virtual CPUs taken away) uses next to none; a thread holding the
# interpreter uses what the host gives it, 40 % of a core beside two CPU burners at equal
# priority and more at the unit's nice -5.
OWN_CPU_SHARE = 0.2
# A watch that asked for the interpreter's lock at least this often (one switch per this many
# seconds of the stall) was waiting for it, not for the host: it asks every 5 ms.
GIL_ASK_PERIOD_S = 0.05
_STATUS = "/proc/thread-self/status"
HOST_STALL_MARK = "the host did not let this service run"  # in a failed job's message
OWN_STALL_MARK = "this service kept its own threads from running"
BLOCKED_STALL_MARK = "a thread of this service was blocked while it held the interpreter"
KINDS = ("host", "own", "blocked")


@dataclass(frozen=True)
class Stall:
    """A late wake: when it ended (monotonic s), how late it was, and the CPU time the
    service's process used over the interval it spans."""

    at_s: float
    late_s: float
    cpu_s: float
    switches: int = 0  # the watch thread's voluntary context switches meanwhile

    @property
    def kind(self) -> str:
        """``own``: the service ran through it; ``blocked``: the watch waited all along for
        the interpreter's lock, held by a thread that used no CPU; ``host``: the watch was
        not run at all."""
        if self.cpu_s >= OWN_CPU_SHARE * self.late_s:
            return "own"
        if self.switches >= self.late_s / GIL_ASK_PERIOD_S:
            return "blocked"
        return "host"


def voluntary_switches(tid: int | None = None) -> int:
    """A thread's voluntary context switches so far (this one's when ``tid`` is None; 0 where
    the kernel does not say)."""
    path = _STATUS if tid is None else f"/proc/self/task/{tid}/status"
    try:
        with open(path, encoding="ascii") as f:
            for line in f:
                if line.startswith("voluntary_ctxt_switches:"):
                    return int(line.split()[1])
    except (OSError, ValueError):
        pass
    return 0


class HostWatch:
    def __init__(self, period_s: float = PERIOD_S, traces: StallTraces | None = None) -> None:
        """``traces``: write every thread's stack when the service stands still for seconds
        (:mod:`cell.supervision.stall_traces`; ``cell serve`` does)."""
        self.period_s = period_s
        self.traces = traces
        self._late: deque[Stall] = deque()  # oldest first
        # every late wake since the start, by its kind (KINDS)
        self.counts = dict.fromkeys(KINDS, 0)
        self.seconds = dict.fromkeys(KINDS, 0.0)
        # when the watch's next wake is due, and the process's CPU time at its last one: a
        # failure seen right after a stall may be seen before the watch has woken from it
        self._due_s: float | None = None
        self._cpu_at_wake_s = 0.0
        self._switches_at_wake = 0
        self._tid: int | None = None  # the watch thread's, for reading its switches
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
        if self.traces is not None:
            self.traces.close()

    def _run(self) -> None:
        traces = self.traces
        self._tid = threading.get_native_id()
        due = time.monotonic() + self.period_s
        cpu_before, switches_before = time.process_time(), voluntary_switches()
        self._expect(due, cpu_before, switches_before)
        while not self._stop.wait(max(0.0, due - time.monotonic())):
            now, cpu, switches = time.monotonic(), time.process_time(), voluntary_switches()
            self.woke(now, now - due, cpu - cpu_before, switches - switches_before)
            if traces is not None:
                traces.ended(now - due, cpu - cpu_before)
                traces.arm(now)
            due, cpu_before, switches_before = now + self.period_s, cpu, switches
            self._expect(due, cpu, switches)

    def _expect(self, due_s: float, cpu_s: float, switches: int) -> None:
        with self._lock:
            self._due_s, self._cpu_at_wake_s = due_s, cpu_s
            self._switches_at_wake = switches

    def _ongoing(self, now_s: float) -> Stall | None:
        """The stall the watch has not woken from yet (None: its wake is not overdue)."""
        with self._lock:
            due, cpu_before = self._due_s, self._cpu_at_wake_s
            tid, switches_before = self._tid, self._switches_at_wake
        if due is None or now_s - due < NOTE_S:
            return None
        switches = 0 if tid is None else voluntary_switches(tid) - switches_before
        return Stall(now_s, now_s - due, time.process_time() - cpu_before, max(0, switches))
    def woke(self, now_s: float, late_s: float, cpu_s: float = 0.0,
             switches: int = 0) -> None:
        """One wake, ``late_s`` after it was due, the process having used ``cpu_s`` of CPU
        and the watch thread switched out ``switches`` times since the last one (the watch's
        thread; tests feed it)."""
        if late_s < NOTE_S:
            return
        stall = Stall(now_s, late_s, cpu_s, switches)
        by = stall.kind
        with self._lock:
            self.counts[by] += 1
            self.seconds[by] += late_s
            self._late.append(stall)
            while self._late and self._late[0].at_s < now_s - KEEP_S:
                self._late.popleft()

    def worst(self, since_s: float, until_s: float | None = None) -> Stall | None:
        """The longest stall that overlapped ``[since_s, until_s]`` (monotonic s), None when
        none was noted."""
        until = time.monotonic() if until_s is None else until_s
        with self._lock:
            overlapping = [s for s in self._late
                           if s.at_s >= since_s and s.at_s - s.late_s <= until]
        ongoing = self._ongoing(until)
        if ongoing is not None:
            overlapping.append(ongoing)
        return max(overlapping, key=lambda s: s.late_s, default=None)

    def note(self, since_s: float, now_s: float | None = None) -> str | None:
        """A sentence for a failure at ``now_s`` when the service was held still for
        ``STALL_S`` or more since ``since_s`` (at most ``WINDOW_S`` back), else None: by the
        host, or by one of its own threads."""
        now = time.monotonic() if now_s is None else now_s
        stall = self.worst(max(since_s, now - WINDOW_S), now)
        if stall is None or stall.late_s < STALL_S:
            return None
        when = (f"for {stall.late_s:.2f} s, {now - stall.at_s:.1f} s before this failure "
                f"(the service used {stall.cpu_s:.2f} s of CPU meanwhile)")
        if stall.kind == "own":
            return (f"{OWN_STALL_MARK} {when}: a computation held the interpreter; a defect "
                    "of the service, not of the device or the host")
        if stall.kind == "blocked":
            return (f"{BLOCKED_STALL_MARK} {when}: in the kernel (a page read back from disk, "
                    "kernel work the host starved) or in a call that does not release it; "
                    "the stacks are in stall-traces.txt beside the job database")
        return (f"{HOST_STALL_MARK} {when}: the host is overloaded (CPU-bound neighbours, or "
                "a virtual machine's CPUs taken away)")
