"""What of the service's start still runs in the background.

``cell serve`` answers as soon as its app is built; the arm's and camera's first connect, the
gripper's activation and the PLC servers' listening sockets finish behind it. ``/health``
says ``starting`` while any of them runs, so a client that waits for the service waits for
all of them, and a device that is missing only because its first try has not ended yet raises
no alarm.
"""

from __future__ import annotations

import threading


class Startup:
    """Named parts of the start that have begun and not yet ended (thread-safe)."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._running: set[str] = set()

    def begin(self, part: str) -> None:
        with self._lock:
            self._running.add(part)

    def end(self, part: str) -> None:
        """The part has ended, however it ended (a failure is reported by the part itself)."""
        with self._lock:
            self._running.discard(part)

    @property
    def running(self) -> list[str]:
        with self._lock:
            return sorted(self._running)

    @property
    def active(self) -> bool:
        with self._lock:
            return bool(self._running)
