"""CPU-burning helper processes: the loaded 2-core host the simulator must cope with.

Used by the peer-client tests and the bench. Each burner is a child process that spins for at
most ``max_s`` seconds and then exits by itself, so a crashed test cannot leave it behind.
"""

from __future__ import annotations

import subprocess
import sys
from collections.abc import Iterator
from contextlib import contextmanager

_SPIN = "import time\nend = time.monotonic() + {max_s}\nwhile time.monotonic() < end:\n    pass\n"


@contextmanager
def cpu_burners(count: int = 2, max_s: float = 120.0) -> Iterator[list[subprocess.Popen[bytes]]]:
    """``count`` processes each keeping one core busy, for the ``with`` block (<= max_s)."""
    procs = [subprocess.Popen([sys.executable, "-c", _SPIN.format(max_s=float(max_s))])
             for _ in range(count)]
    try:
        yield procs
    finally:
        for p in procs:
            if p.poll() is None:
                p.kill()
        for p in procs:
            p.wait(timeout=5.0)
