"""The controller's 500 Hz thread: steps the arm on the controller clock.

A background thread runs one controller cycle every 2 ms of wall-clock time: the scheduled
events, the active command's step, then the protocol layer's hook, each cycle with its own
timestamp, catching up cycle by cycle after a host stall. When nothing moves and nobody needs
every cycle it sleeps on the engine's condition, so an idle engine costs next to no CPU on a
shared machine.
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable

from fakes.ur_sim.arm_core import ArmCore
from fakes.ur_sim.clock import MAX_CATCH_UP_CYCLES
from fakes.ur_sim.state import CYCLE_S

log = logging.getLogger("fakes.ur_sim.engine")


class CycleLoop:
    """The stepping thread of one arm; ``run_events(now)`` and ``step(now, dt)`` are called
    with the lock held, the hook without it."""

    def __init__(self, core: ArmCore, run_events: Callable[[float], None],
                 step: Callable[[float, float], None]) -> None:
        self._core = core
        self._run_events = run_events
        self._step = step
        self._thread: threading.Thread | None = None

    def start(self) -> None:
        with self._core.cond:
            if self._thread is not None:
                return
            self._thread = threading.Thread(target=self._run, name="ur-sim-engine", daemon=True)
            self._thread.start()

    def close(self) -> None:
        core = self._core
        with core.cond:
            core.alive = False
            core.cond.notify_all()
        if self._thread is not None and self._thread is not threading.current_thread():
            self._thread.join(timeout=2.0)

    def _run(self) -> None:
        core = self._core
        while True:
            with core.cond:
                if not core.alive:
                    return
                due = core.clock.due()
                if not core.cycling():
                    core.clock.cycles = max(core.clock.cycles, due)
                    self._run_events(core.now())
                    if not core.cycling():
                        period = core.idle_period_s if core.hook is not None else 1.0
                        wake = min((t for t, _ in core.timers),
                                   default=time.monotonic() + period)
                        core.cond.wait(timeout=max(0.0, min(wake - time.monotonic(), period)))
                        hook = core.hook if core.alive and not core.cycling() else None
                        if hook is None:
                            continue
                    else:
                        hook = None
                else:
                    hook = None
            if hook is not None:
                self._call_hook(hook)
                continue
            self._cycle_until(due)

    def _cycle_until(self, due: int) -> None:
        """Run controller cycles up to ``due`` (catching up after a stall), then wait for the
        next one."""
        core = self._core
        if due - core.clock.cycles > MAX_CATCH_UP_CYCLES:
            with core.cond:
                core.clock.skip_long_stall(due)
        while core.alive:
            with core.cond:
                if core.clock.cycles >= due or not core.cycling():
                    break
                core.clock.cycles += 1
                now = core.now()
                self._run_events(now)
                if core.busy():
                    self._step(now, CYCLE_S)
                hook = core.hook
            if hook is not None:
                self._call_hook(hook)
        delay = core.clock.delay_to_next_cycle_s()
        if delay > 0:
            time.sleep(delay)

    @staticmethod
    def _call_hook(hook: Callable[[], None]) -> None:
        try:
            hook()
        except Exception:  # the controller cycle must survive anything one step does
            log.exception("controller cycle hook failed")

