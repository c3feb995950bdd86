"""Refused requests in the audit log: one row each, up to a budget per second, so a flood of
bad requests cannot fill the log or slow the answers (the rest are counted in the next row)."""

from __future__ import annotations

import logging
import threading
import time
from typing import Any

log = logging.getLogger(__name__)

AUDIT_REFUSALS_PER_S = 50  # beyond this, refusals are counted, not written one by one


class _RefusalBudget:
    """Keeps a flood of refused requests (a scanner, a misconfigured client) from filling the
    audit table: past the budget in one second, rows are skipped and their number is written
    with the next row that fits."""

    def __init__(self) -> None:
        self.lock = threading.Lock()
        self.second = 0
        self.used = 0
        self.skipped = 0

    def take(self) -> tuple[bool, int]:
        """(may write now, rows skipped since the last written one)."""
        now = int(time.monotonic())
        with self.lock:
            if now != self.second:
                self.second, self.used = now, 0
            if self.used >= AUDIT_REFUSALS_PER_S:
                self.skipped += 1
                return False, 0
            self.used += 1
            skipped, self.skipped = self.skipped, 0
            return True, skipped


def audit_refusal(app: Any, caller: str, method: str, route: str, status: int, code: str,
                  message: str) -> None:
    """One audit row per refused request; never lets a logging failure change the answer."""
    try:
        budget = getattr(app.state, "refusal_budget", None)
        if budget is None:
            budget = app.state.refusal_budget = _RefusalBudget()
        ok, skipped = budget.take()
        if not ok:
            return
        params: dict[str, Any] = {"status": status}
        if skipped:
            params["refusals_not_written_before"] = skipped
        app.state.cell.jobs.audit(caller, f"{method} {route}", params, f"refused:{code}",
                                  message[:500])
    except Exception:  # the answer matters more than the audit row
        log.exception("could not audit a refused request")
