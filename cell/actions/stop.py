"""THE stop path: one thread of its own that does nothing but tell the arm to stop.

Every way the cell can be stopped (HTTP ``/stop``, the dead-man expiry of a continuous jog,
shutdown, and later OPC UA and XML-RPC) calls :meth:`StopLine.stop`. It

1. sets the motion slot holder's cancel flag in the caller's thread (an ``Event``: no further
   motion command can pass the guard from that instant),
2. hands the request to the stop thread, which is idle until then and shares no queue, pool
   or lock with any other work, so a queue of reads or jobs can never delay it; requests that
   arrive while a stop is being sent are answered by the next one (a stop is idempotent),
3. tells the arm to stop (``GuardedArm.stop`` records ``Commanded(kind="stop")``), then halts
   the gripper if a command of the cell may be moving it, and only after that finishes the
   cancelled job's bookkeeping: counts, audit, the ``stop`` event.

Both stops are sent holding the command gate (:class:`cell.motion.guard.CommandGate`), so a
command that passed its last check before the flag was set reaches its device before the stop
does, and the stop ends it: once the answer says ``stopped``, nothing the cell commanded
before or during the stop moves on.

The caller gets the outcome with ``commanded_monotonic_s``, the ``time.monotonic()`` at which
the stop was handed to the arm adapter, and ``sent_monotonic_s`` when the adapter returned (the
controller had it), so latency can be measured from any process on the host.
"""

from __future__ import annotations

import logging
import queue
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

from cell.core import CellCore
from cell.motion.guard import Motion
from drivers.errors import ConnectionLostError, DriverError

log = logging.getLogger(__name__)
STOP_DECEL_MM_S2 = 2000.0
ANSWER_TIMEOUT_S = 10.0  # the adapter's own call deadline is shorter; this is a backstop

Done = Callable[[dict[str, Any]], None]


@dataclass
class _Request:
    caller: str
    reason: str
    requested_s: float
    motion: Motion | None
    done: Done | None = None
    result: dict[str, Any] | None = None
    finished: threading.Event = field(default_factory=threading.Event)


HaltGripper = Callable[[], str | None]  # the error text when it could not, else None


class StopLine:
    def __init__(self, core: CellCore, halt_gripper: HaltGripper | None = None) -> None:
        self.core = core
        self._halt_gripper = halt_gripper
        self._queue: queue.SimpleQueue[_Request | None] = queue.SimpleQueue()
        self._thread = threading.Thread(target=self._loop, name="cell-stop", daemon=True)
        self._thread.start()
        self._closed = False

    def close(self) -> None:
        if not self._closed:
            self._closed = True
            self._queue.put(None)
            self._thread.join(timeout=ANSWER_TIMEOUT_S)

    def stop(self, caller: str, reason: str = "requested") -> dict[str, Any]:
        """Stop now and wait for the outcome (see the module doc)."""
        req = self.submit(caller, reason)
        if not req.finished.wait(ANSWER_TIMEOUT_S):
            return {"stopped": False, "cancelled": None if req.motion is None else
                    req.motion.name, "job_id": None, "arm_error": "the stop thread did not "
                    f"answer within {ANSWER_TIMEOUT_S:g} s", "commanded_monotonic_s": None,
                    "sent_monotonic_s": None}
        assert req.result is not None
        return req.result

    def submit(self, caller: str, reason: str = "requested", done: Done | None = None
               ) -> _Request:
        """Stop without waiting: ``done(result)`` is called from the stop thread (an event
        loop passes a ``call_soon_threadsafe`` wrapper)."""
        motion = self.core.slot.cancel()  # the flag first: nothing new passes the guard
        req = _Request(caller, reason, time.monotonic(), motion, done)
        if self._closed:
            self._serve([req])
        else:
            self._queue.put(req)
        return req

    def _loop(self) -> None:
        while True:
            req = self._queue.get()
            if req is None:
                return
            batch = [req]
            while True:  # stops that queued up while the last one was sent: one stop for all
                try:
                    more = self._queue.get_nowait()
                except queue.Empty:
                    break
                if more is None:
                    self._serve(batch)
                    return
                batch.append(more)
            try:
                self._serve(batch)
            except Exception:  # the stop thread must never die
                log.exception("stop failed")
                for r in batch:
                    if not r.finished.is_set():
                        r.result = {"stopped": False, "cancelled": None, "job_id": None,
                                    "arm_error": "internal error in the stop path",
                                    "commanded_monotonic_s": None, "sent_monotonic_s": None}
                        r.finished.set()

    def _serve(self, batch: list[_Request]) -> None:
        commanded_s = time.monotonic()
        arm_error = self._stop_arm()
        sent_s = time.monotonic()
        gripper_error = self._stop_gripper()
        motion = self.core.slot.cancel()  # a motion that started meanwhile ends too
        core = self.core
        for req in batch:
            cancelled = req.motion or motion
            job_id = None if cancelled is None else cancelled.job_id
            result = {"stopped": arm_error is None and gripper_error is None,
                      "cancelled": None if cancelled is None else cancelled.name,
                      "job_id": job_id, "arm_error": arm_error,
                      "commanded_monotonic_s": commanded_s, "sent_monotonic_s": sent_s}
            if gripper_error is not None:
                result["gripper_error"] = gripper_error
            core.stats.count_stop()
            try:
                core.audit.record(req.caller, "stop", {"reason": req.reason},
                                  "ok" if arm_error is None else "arm_error", arm_error or "",
                                  job_id, time.time() - (time.monotonic() - req.requested_s))
            except Exception:  # the audit log is not a reason to withhold the answer
                log.exception("could not audit a stop")
            core.events.publish("stop", {k: v for k, v in result.items()
                                         if not k.endswith("_monotonic_s")})
            req.result = result
            req.finished.set()
            if req.done is not None:
                try:
                    req.done(result)
                except Exception:
                    log.exception("stop callback failed")

    def _stop_gripper(self) -> str | None:
        if self._halt_gripper is None:
            return None
        try:
            return self._halt_gripper()
        except Exception as err:  # the stop's answer must come whatever the gripper does
            log.exception("halting the gripper failed")
            return f"gripper: {err}"

    def _stop_arm(self) -> str | None:
        """Stop the arm now; the driver's error text if it could not, else None."""
        try:
            self.core.arm.stop(decel_mm_s2=STOP_DECEL_MM_S2)
        except ConnectionLostError as err:
            return (f"{err}; the link is down, and the cell tells the controller to stop as "
                    "soon as it answers again, before anything else")
        except DriverError as err:
            return str(err)
        return None
