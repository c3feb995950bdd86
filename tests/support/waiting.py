"""The one way a test waits: poll a condition until it holds, or fail saying what it waited for.

Tests that depend on timing run on a loaded 2-core machine, so none of them sleeps a fixed time
and hopes; each polls what it needs and has a bound generous enough for that machine.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from typing import TypeVar

T = TypeVar("T")


def wait_until(pred: Callable[[], T], timeout_s: float = 5.0, what: str = "the condition",
               poll_s: float = 0.02) -> T:
    """The first truthy value of ``pred()``; AssertionError once ``timeout_s`` has passed
    (``pred`` is asked once more at the deadline, so a slow poll never loses a late truth)."""
    deadline = time.monotonic() + timeout_s
    while True:
        value = pred()
        if value:
            return value
        if time.monotonic() >= deadline:
            value = pred()
            if value:
                return value
            raise AssertionError(f"timed out after {timeout_s:g} s waiting for {what}")
        time.sleep(poll_s)
