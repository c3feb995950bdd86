"""Fan-out of cell events (state at camera rate, job and jog changes) to many listeners.

Each subscriber gets its own bounded queue; a slow listener (a stalled browser tab) loses its
oldest events instead of blocking the cell or growing memory.
"""

from __future__ import annotations

import contextlib
import queue
import threading
import time
from collections.abc import Callable
from typing import Any


class Subscription:
    def __init__(self, bus: EventBus, maxsize: int) -> None:
        self._bus = bus
        self.queue: queue.Queue[dict[str, Any]] = queue.Queue(maxsize=maxsize)
        # told after each event is queued (an event loop's waker: streams wait, not poll)
        self.notify: Callable[[], None] | None = None

    def get(self, timeout_s: float) -> dict[str, Any] | None:
        try:
            return self.queue.get(timeout=timeout_s)
        except queue.Empty:
            return None

    def close(self) -> None:
        self._bus.unsubscribe(self)

    def __enter__(self) -> Subscription:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


class EventBus:
    def __init__(self, maxsize: int = 200) -> None:
        self._subs: list[Subscription] = []
        self._lock = threading.Lock()
        self._maxsize = maxsize

    @property
    def n_subscribers(self) -> int:
        with self._lock:
            return len(self._subs)

    def subscribe(self) -> Subscription:
        sub = Subscription(self, self._maxsize)
        with self._lock:
            self._subs.append(sub)
        return sub

    def unsubscribe(self, sub: Subscription) -> None:
        with self._lock:
            if sub in self._subs:
                self._subs.remove(sub)

    def publish(self, event_type: str, data: dict[str, Any]) -> None:
        event = {"type": event_type, "time": time.time(), **data}
        with self._lock:
            subs = list(self._subs)
        for sub in subs:
            while True:
                try:
                    sub.queue.put_nowait(event)
                    break
                except queue.Full:
                    with contextlib.suppress(queue.Empty):
                        sub.queue.get_nowait()
            notify = sub.notify
            if notify is not None:
                try:
                    notify()
                except RuntimeError:  # its event loop has closed: the stream is gone
                    sub.notify = None
