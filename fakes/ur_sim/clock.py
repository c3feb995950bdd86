"""The simulated controller's own clock: 500 Hz cycles counted from its start.

Time on the controller is cycles, not the host's reading at the moment: after a host stall the
engine runs every missed cycle with its own timestamp, as a real controller never stalls. This
keeps that count and its arithmetic apart from the thread that advances it.
"""

from __future__ import annotations

import time

from fakes.ur_sim.state import CYCLE_S

MAX_CATCH_UP_CYCLES = 500  # a host stall up to 1 s is caught up cycle by cycle


class CycleClock:
    """Cycles since start; callers hold the engine lock."""

    def __init__(self) -> None:
        self.t0 = time.monotonic()
        self.cycles = 0  # controller cycles since t0: the controller's own clock
        self.skipped_cycles = 0  # cycles lost to host stalls longer than the catch-up window

    def now(self) -> float:
        """The controller clock, as a ``time.monotonic()`` instant: t0 + cycles * 2 ms."""
        return self.t0 + self.cycles * CYCLE_S

    def due(self) -> int:
        """The cycle the host clock says it is."""
        return int((time.monotonic() - self.t0) / CYCLE_S)

    def skip_long_stall(self, due: int) -> None:
        """A stall longer than the catch-up window is skipped; the skip is visible as a jump in
        the controller clock (RTDE ``timestamp``), as a real gap would be."""
        behind = due - self.cycles
        if behind > MAX_CATCH_UP_CYCLES:
            self.cycles = due - MAX_CATCH_UP_CYCLES
            self.skipped_cycles += behind - MAX_CATCH_UP_CYCLES

    def delay_to_next_cycle_s(self) -> float:
        """Host seconds until the next cycle is due (<= 0: already due)."""
        return self.t0 + (self.cycles + 1) * CYCLE_S - time.monotonic()
