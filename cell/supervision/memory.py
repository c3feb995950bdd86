"""The service's native heap over days: glibc malloc arenas bounded, freed pages handed back.

The service allocates megabyte buffers (camera frames, overlays, JPEGs, OpenCV and numba
work arrays) from many threads: a thread per job, the HTTP thread pool, the camera, the
supervisors. glibc gives threads up to 8 arenas per core and returns an arena's freed memory to
the kernel only from the top of its heap, so freed holes between live blocks stay resident:
on a soak (``cell bench soak``, docs/performance.md) ~15 arenas' resident memory grew 17 -> 40
MB in 6 minutes while the main heap stayed at 46 MB, and ``malloc_trim(0)`` took 17 MB back.
Two measures, both in the ``cell serve`` process:

- :func:`limit_arenas`: at most ``ARENA_MAX`` arenas, set before the service starts threads
  (an explicit ``MALLOC_ARENA_MAX`` in the environment is left to glibc);
- :class:`Trimmer`: a low-rate housekeeping thread calling ``malloc_trim(0)``, which hands the
  free pages inside every arena back to the kernel (``madvise``), every ``TRIM_PERIOD_S``
  (``CELL_MALLOC_TRIM_S`` in the environment: another period, 0: off).

And :func:`keep_heap`, since the trimmer hands memory back: glibc's own give-and-take turned
down. By default a buffer above a (moving) threshold is its own ``mmap``, and a heap whose top
is free shrinks at once (``brk``, ``madvise``): a soak's service made ~100 such memory-map
changes a second, each from the thread that allocated or freed a frame, holding the
interpreter's lock. A change that grows a mapping waits for the lock of the process's
anonymous memory, which the kernel's page-reclaim monitor (DAMON) holds while it walks that
memory; beside CPU-bound processes the service stood still behind it for 3-53 s. With buffers
up to 32 MB taken from the heap, and the heap kept until the trimmer's next pass, the jobs'
threads seldom change the map.

Neither changes what Python or numpy allocate; without glibc (musl, macOS) both do nothing.

And one against the opposite: pages taken away. A kernel that reclaims cold page cache
proactively (DAMON's ``pageout``, or plain memory pressure) drops the service's library code
(OpenCV, numpy, numba's LLVM, ur_rtde's bindings) once it has not run for a while; the next
call reads it back from disk, and a thread that faults holding the interpreter's lock holds
the whole service for as long as that read takes. :func:`lock_file_pages` locks every
file-backed mapping once it is touched (``mlock2(MLOCK_ONFAULT)``): nothing is read in ahead,
and what the service has run stays in RAM. Anonymous memory (the heap) is left alone, so
``malloc_trim`` still hands its holes back; without swap it is never paged out anyway.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import logging
import os
import threading
import time

log = logging.getLogger(__name__)

M_TRIM_THRESHOLD = -1  # mallopt parameters (malloc.h)
M_TOP_PAD = -2
M_MMAP_THRESHOLD = -3
M_ARENA_MAX = -8
ARENA_MAX = 2
MMAP_THRESHOLD_BYTES = 32 << 20  # glibc's upper bound for a 64-bit process
TRIM_THRESHOLD_BYTES = 256 << 20  # the heap shrinks by itself only past this much free top
TOP_PAD_BYTES = 16 << 20  # a heap grows by this much more than asked
_MALLOC_ENV = ("MALLOC_MMAP_THRESHOLD_", "MALLOC_TRIM_THRESHOLD_", "MALLOC_TOP_PAD_")
TRIM_PERIOD_S = 30.0
SLOW_TRIM_S = 0.2  # a trim this long is logged as a warning


def _libc() -> ctypes.CDLL | None:
    name = ctypes.util.find_library("c")
    if name is None:
        return None
    try:
        libc = ctypes.CDLL(name, use_errno=True)
        libc.mallopt  # noqa: B018 - glibc's, absent from other C libraries
        libc.malloc_trim  # noqa: B018
    except (OSError, AttributeError):
        return None
    return libc


def trim_period_s() -> float:
    """The trim period: ``CELL_MALLOC_TRIM_S`` from the environment (0: off), else
    ``TRIM_PERIOD_S``."""
    try:
        return max(0.0, float(os.environ.get("CELL_MALLOC_TRIM_S", TRIM_PERIOD_S)))
    except ValueError:
        return TRIM_PERIOD_S


def limit_arenas(arenas: int = ARENA_MAX) -> bool:
    """Bound glibc's malloc arenas (call before threads start); False when not applied."""
    if "MALLOC_ARENA_MAX" in os.environ:
        return False
    libc = _libc()
    if libc is None:
        return False
    return bool(libc.mallopt(ctypes.c_int(M_ARENA_MAX), ctypes.c_int(arenas)))


def keep_heap() -> bool:
    """Buffers up to ``MMAP_THRESHOLD_BYTES`` from the heap, and a heap that neither shrinks
    nor grows a little at a time (call before threads start); False when not applied:
    ``CELL_MALLOC_KEEP=0``, a glibc tunable in the environment, or no glibc."""
    if os.environ.get("CELL_MALLOC_KEEP", "1") == "0" or any(k in os.environ for k in _MALLOC_ENV):
        return False
    libc = _libc()
    if libc is None:
        return False
    return all(bool(libc.mallopt(ctypes.c_int(param), ctypes.c_int(value))) for param, value in (
        (M_MMAP_THRESHOLD, MMAP_THRESHOLD_BYTES), (M_TRIM_THRESHOLD, TRIM_THRESHOLD_BYTES),
        (M_TOP_PAD, TOP_PAD_BYTES)))


def trim() -> bool:
    """``malloc_trim(0)``: True when memory was released to the kernel."""
    libc = _libc()
    return libc is not None and bool(libc.malloc_trim(ctypes.c_size_t(0)))


class Trimmer:
    """``malloc_trim(0)`` every ``period_s`` on a daemon thread (a few ms each time), and
    with ``lock_pages`` :func:`lock_file_pages` again (libraries loaded since are locked
    too)."""

    def __init__(self, period_s: float = TRIM_PERIOD_S, lock_pages: bool = False) -> None:
        self.period_s = period_s
        self.lock_pages = lock_pages
        self._lock_failed = False
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self.trims = 0

    def start(self) -> None:
        libc = _libc()
        if libc is None or self._thread is not None:
            return
        self._thread = threading.Thread(target=self._run, args=(libc,), name="cell-malloc-trim",
                                        daemon=True)
        self._thread.start()

    def stop(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=2.0)
            self._thread = None

    def _run(self, libc: ctypes.CDLL) -> None:
        while not self._stop.wait(self.period_s):
            if self.lock_pages and not self._lock_failed:
                _, why = lock_file_pages()
                if why is not None:
                    self._lock_failed = True
                    log.warning("library pages are not kept in RAM: %s", why)
            t0 = time.perf_counter()
            released = libc.malloc_trim(ctypes.c_size_t(0))
            self.trims += 1
            took_s = time.perf_counter() - t0
            # a trim holds each arena's lock while it walks it; a thread that allocates
            # meanwhile waits, and one holding the interpreter's lock holds the service
            (log.warning if took_s >= SLOW_TRIM_S else log.debug)(
                "malloc_trim: %s in %.1f ms", "released" if released else "nothing",
                1000.0 * took_s)


MLOCK_ONFAULT = 1  # mlock2 flag (linux/mman.h)


def lock_file_pages(maps: str = "/proc/self/maps") -> tuple[int, str | None]:
    """``mlock2(MLOCK_ONFAULT)`` each readable file-backed mapping of this process (the
    interpreter, the libraries, their data): returns the bytes covered and, when the lock
    stopped short, why (``RLIMIT_MEMLOCK`` too low: the systemd unit sets
    ``LimitMEMLOCK=infinity``; ``CELL_LOCK_FILE_PAGES=0`` in the environment: off)."""
    if os.environ.get("CELL_LOCK_FILE_PAGES", "1") == "0":
        return 0, "off (CELL_LOCK_FILE_PAGES=0)"
    libc = _libc()
    try:
        mlock2 = None if libc is None else libc.mlock2
    except AttributeError:
        mlock2 = None
    if mlock2 is None:
        return 0, "no mlock2 in this C library"
    mlock2.argtypes = (ctypes.c_void_p, ctypes.c_size_t, ctypes.c_int)
    covered = 0
    try:
        with open(maps, encoding="utf-8", errors="replace") as f:
            lines = f.readlines()
    except OSError as err:
        return 0, f"cannot read {maps}: {err}"
    for line in lines:
        fields = line.split(maxsplit=5)
        if len(fields) < 6 or not fields[5].startswith("/") or fields[1][0] != "r":
            continue  # anonymous, [heap], [stack], [vdso], or not readable
        path = fields[5].strip()
        if path.startswith("/dev/") or path.endswith("(deleted)"):
            continue
        start, end = (int(x, 16) for x in fields[0].split("-"))
        if mlock2(start, end - start, MLOCK_ONFAULT) != 0:
            return covered, os.strerror(ctypes.get_errno())
        covered += end - start
    return covered, None
