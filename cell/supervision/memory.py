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

Neither changes what Python or numpy allocate; without glibc (musl, macOS) both do nothing.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import logging
import os
import threading
import time

log = logging.getLogger(__name__)

M_ARENA_MAX = -8  # mallopt parameter (malloc.h)
ARENA_MAX = 2
TRIM_PERIOD_S = 30.0
SLOW_TRIM_S = 0.2  # a trim this long is logged as a warning


def _libc() -> ctypes.CDLL | None:
    name = ctypes.util.find_library("c")
    if name is None:
        return None
    try:
        libc = ctypes.CDLL(name)
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


def trim() -> bool:
    """``malloc_trim(0)``: True when memory was released to the kernel."""
    libc = _libc()
    return libc is not None and bool(libc.malloc_trim(ctypes.c_size_t(0)))


class Trimmer:
    """``malloc_trim(0)`` every ``period_s`` on a daemon thread (a few ms each time)."""

    def __init__(self, period_s: float = TRIM_PERIOD_S) -> None:
        self.period_s = period_s
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
            t0 = time.perf_counter()
            released = libc.malloc_trim(ctypes.c_size_t(0))
            self.trims += 1
            took_s = time.perf_counter() - t0
            # a trim holds each arena's lock while it walks it; a thread that allocates
            # meanwhile waits, and one holding the interpreter's lock holds the service
            (log.warning if took_s >= SLOW_TRIM_S else log.debug)(
                "malloc_trim: %s in %.1f ms", "released" if released else "nothing",
                1000.0 * took_s)
