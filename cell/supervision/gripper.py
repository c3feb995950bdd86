"""Gripper commands, one Modbus transaction at a time, and a cached status that costs reads
nothing.

A command that moves the fingers is a motion like any other: it holds the motion slot (or runs
inside the job that holds it), is sent through the command gate the arm's commands pass, and a
stop halts it (:meth:`GripperService.halt`), so STOP stops everything the cell commanded.

A gripper that times out (a serial link gone quiet) takes a second per transaction; reading it
inside ``/status`` made every status poll wait for that. Here a background thread refreshes the
status twice a second and on every command, and readers get the last one with its age; a fault
or a lost link is published once (``gripper`` events) so the operator sees it. A background
read that fails once is counted, not reported: the link is faulty when two in a row fail.
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable
from contextlib import AbstractContextManager, nullcontext
from typing import Any

from cell.error_codes import ErrorCode
from cell.errors import LimitError, UnavailableError
from cell.jobs.audit import Auditor
from cell.jobs.events import EventBus
from cell.motion.guard import CommandGate, Motion, MotionSlot, driver_error
from cell.supervision.startup import Startup
from drivers.errors import DriverError
from drivers.gripper import Gripper, GripperStatus

log = logging.getLogger(__name__)
POLL_PERIOD_S = 0.5
STARTUP_PART = "gripper"
NOTE_WINDOW_S = 3.0  # a failed read looks this far back for a stall (its timeouts and retry)
# Background reads that must fail in a row before the link counts as faulty (each read is
# already tried ``[gripper] retries`` more times): one missed answer on a serial line is noise
# to count (``missed_reads``), not an alarm; a command's failed read is reported at once.
MISSED_READS_FOR_FAULT = 2
ACTIONS = ("open", "close", "move", "activate")


class GripperService:
    def __init__(self, gripper: Gripper | None, audit: Auditor, events: EventBus,
                 slot: MotionSlot | None = None, gate: CommandGate | None = None,
                 startup: Startup | None = None,
                 host_note: Callable[[float], str | None] | None = None) -> None:
        """``host_note(since_s)``: why the service was held still since then, if it was
        (cell.supervision.host_watch); a read that failed meanwhile says so, and so does the
        alarm raised from it."""
        self.gripper = gripper
        self.host_note = host_note
        self.startup = startup if startup is not None else Startup()
        self.audit = audit
        self.events = events
        self.slot = slot if slot is not None else MotionSlot()
        self.gate = gate if gate is not None else CommandGate()
        self._commanding = False  # a command of the cell may be moving the fingers
        self._connected = False  # connect() has succeeded once; the driver reopens a lost link
        self.missed_reads = 0  # background status reads that failed, since the start
        self._misses_in_row = 0
        self._bus_lock = threading.Lock()  # one Modbus transaction at a time
        self._lock = threading.Lock()
        self._last: dict[str, Any] | None = None
        self._last_t = 0.0
        self._error: str | None = None
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None

    def start(self, connect_in_background: bool = False) -> None:
        """Connect and activate the gripper, then poll it; ``connect_in_background``: the
        poll thread makes that first try (a part of the start, :mod:`cell.supervision.startup`)
        and this returns at once."""
        if self.gripper is None:
            return
        if connect_in_background:
            self.startup.begin(STARTUP_PART)
        else:
            self._first_connect()
        self._thread = threading.Thread(target=self._poll, args=(connect_in_background,),
                                        name="cell-gripper", daemon=True)
        self._thread.start()

    def _first_connect(self) -> None:
        with self._bus_lock:
            if not self._connect():
                log.warning("gripper not available at start: %s", self._error)

    def close(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=3.0)

    def status(self) -> dict[str, Any] | None:
        """The last status read (never waits on the serial line), with its age."""
        if self.gripper is None:
            return None
        with self._lock:
            age = None if self._last is None else max(0.0, time.monotonic() - self._last_t)
            base = dict(self._last) if self._last is not None else {}
            return {**base, "age_s": age, "error": self._error}

    def command(self, caller: str, action: str, position_mm: float | None = None,
                speed_pct: float = 100.0, force_pct: float = 50.0,
                wait: bool = True, motion: Motion | None = None) -> dict[str, Any]:
        """One gripper command, audited. It takes the motion slot (``busy`` while the arm
        moves), unless ``motion`` says which job's motion it belongs to."""
        params = {"action": action, "position_mm": position_mm, "speed_pct": speed_pct,
                  "force_pct": force_pct, "wait": wait}
        with self.audit.command(caller, "gripper", params):
            g = self.gripper
            if g is None:
                raise UnavailableError(ErrorCode.gripper_unavailable, "this cell has no gripper")
            if action not in ACTIONS:
                raise LimitError(ErrorCode.invalid_request, f"unknown gripper action {action!r}")
            if action == "move" and position_mm is None:
                raise LimitError(ErrorCode.invalid_request, "move needs position_mm")
            holding: AbstractContextManager[Motion] = (
                self.slot.hold("gripper") if motion is None else nullcontext(motion))
            with holding as held, self._bus_lock:
                try:
                    st = self._run(g, held, action, position_mm, speed_pct, force_pct, wait)
                except DriverError as err:
                    self._set(None, str(err))
                    raise driver_error(err, f"gripper {action}", device="gripper") from err
            self._set(st, None)
            return st.as_dict()

    def _run(self, g: Gripper, motion: Motion, action: str, position_mm: float | None,
             speed_pct: float, force_pct: float, wait: bool) -> GripperStatus:
        """Send through the gate without waiting, then (``wait``) watch the fingers stop; a
        stop that halted them ends the command ``cancelled``."""
        if action == "activate":
            # the activation stroke runs to its end whatever rGTO says, so a stop cannot
            # halt it, and the gate is not held for its seconds (a stop would wait for them)
            motion.raise_if_cancelled("before the gripper's activation")
            return g.activate()
        try:
            with self.gate.command(motion, f"gripper {action}"):
                self._commanding = True
                if action == "open":
                    st = g.open(wait=False)
                elif action == "close":
                    st = g.close(wait=False)
                else:
                    assert position_mm is not None
                    st = g.move(position_mm, speed_pct, force_pct, wait=False)
            if not wait:
                return st
            st = g.wait_for_motion()
            motion.raise_if_cancelled(f"while the gripper moved ({action})")
            return st
        finally:
            if wait:
                self._commanding = False

    def halt(self) -> str | None:
        """Halt the fingers if a command of the cell may be moving them (the stop path calls
        this after the arm's stop); the driver's error text when it could not, else None."""
        g = self.gripper
        if g is None:
            return None
        with self.gate.stopping():
            if not self._commanding:
                return None
            try:
                st = g.stop()
            except DriverError as err:
                self._set(None, str(err))
                return f"gripper: {err}"
            self._commanding = False
        self._set(st, None)
        return None

    def _connect(self) -> bool:
        """Open the link and activate the gripper (an activated one is left as it is); the
        caller holds the bus. A gripper that was off or unplugged at start is connected by the
        poll as soon as it answers, as it would have been at start."""
        assert self.gripper is not None
        try:
            self.gripper.connect()
            st = self.gripper.activate()
        except DriverError as err:
            self._set(None, str(err))
            return False
        self._connected = True
        self._set(st, None)
        return True

    def _poll(self, first_connect: bool) -> None:
        assert self.gripper is not None
        if first_connect:
            try:
                self._first_connect()
            finally:
                self.startup.end(STARTUP_PART)
        while not self._stop.wait(POLL_PERIOD_S):
            if not self._bus_lock.acquire(timeout=0.05):
                continue  # a command holds the line and refreshes the status itself
            try:
                if not self._connected:
                    if self._connect():
                        log.info("gripper connected")
                    continue
                st = self.gripper.status()
            except DriverError as err:
                self.missed_reads += 1
                self._misses_in_row += 1
                if self._misses_in_row >= MISSED_READS_FOR_FAULT:
                    self._set(None, self._explained(str(err)))
                else:
                    log.info("gripper status read missed (%s); read again in %.1f s",
                             self._explained(str(err)), POLL_PERIOD_S)
                continue
            finally:
                self._bus_lock.release()
            self._misses_in_row = 0
            self._set(st, None)

    def _explained(self, error: str) -> str:
        """The error, and the stall of the service that came before it, if one did."""
        note = None if self.host_note is None else self.host_note(
            time.monotonic() - NOTE_WINDOW_S)
        return error if note is None else f"{error} ({note})"

    def _set(self, st: GripperStatus | None, error: str | None) -> None:
        fault = error if error is not None else (st.fault if st is not None else None)
        with self._lock:
            before = self._error if self._error is not None else (
                None if self._last is None else self._last.get("fault"))
            if st is not None:
                self._last, self._last_t = st.as_dict(), time.monotonic()
            self._error = error
        if fault != before:
            if fault is not None:
                log.warning("gripper fault: %s", fault)
            self.events.publish("gripper", {"fault": fault})
