"""Where every thread of the service stood when it stood still for seconds.

A stall the service itself causes while using no CPU (a thread that blocks in a call that keeps
the interpreter's lock) looks from inside like a host that did not schedule the process: no
Python thread runs, not even the one that would look. ``faulthandler``'s watchdog is a thread
of C that needs no interpreter lock: armed again every second by the host watch, it fires
only when the watch has not come back for ``AFTER_S`` and writes every thread's stack to a
file in the service's state directory; when the stall ends the watch adds one line with its
length and the time. The file is capped (``MAX_BYTES``): past it, nothing more is armed.
"""

from __future__ import annotations

import faulthandler
import logging
import time
from pathlib import Path
from typing import IO

log = logging.getLogger(__name__)
AFTER_S = 2.0  # a stall this long gets its stacks written
REARM_S = 1.0  # how often the watch arms the dump again (each arming starts a C thread)
MAX_BYTES = 2_000_000


class StallTraces:
    """Armed by the host watch's thread (one process may have one such dump armed)."""

    def __init__(self, path: Path) -> None:
        self.path = path
        self._file: IO[str] | None = None
        self._armed_at_s = 0.0
        self.full = False

    def arm(self, now_s: float) -> None:
        """Arm the dump again when the last arming is ``REARM_S`` old (cheap otherwise)."""
        if self.full or now_s - self._armed_at_s < REARM_S:
            return
        try:
            if self._file is None:
                self.path.parent.mkdir(parents=True, exist_ok=True)
                self._file = self.path.open("a", encoding="utf-8")
            if self.path.stat().st_size > MAX_BYTES:
                self.full = True
                self.disarm()
                log.warning("stall traces: %s is full (%d bytes); no more are written",
                            self.path, MAX_BYTES)
                return
            faulthandler.dump_traceback_later(AFTER_S + REARM_S, file=self._file)
        except OSError as err:  # a full disk: the traces are a diagnosis, not a duty
            log.warning("stall traces: cannot write %s: %s", self.path, err)
            self.full = True
            return
        self._armed_at_s = now_s

    def ended(self, late_s: float, cpu_s: float) -> None:
        """A stall the dump may have caught has ended: say how long it was and when."""
        if self._file is None or late_s < AFTER_S:
            return
        stamp = time.strftime("%Y-%m-%d %H:%M:%S %z")
        try:
            self._file.write(f"-- stall of {late_s:.2f} s ended at {stamp} (the service used "
                             f"{cpu_s:.2f} s of CPU meanwhile); the stacks above are from "
                             f"{AFTER_S + REARM_S:.0f} s or less into it\n")
            self._file.flush()
        except OSError:
            pass

    def disarm(self) -> None:
        faulthandler.cancel_dump_traceback_later()

    def close(self) -> None:
        self.disarm()
        if self._file is not None:
            self._file.close()
            self._file = None
