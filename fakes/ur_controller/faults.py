"""Fault injection for tests: what goes wrong with real controllers, on demand.

- ``drop_connections``: every client connection closed by the controller (FIN, or RST).
- ``stall_stream``: RTDE data packages stop for a while; connections stay open.
- ``protective_stop`` / ``emergency_stop``: a safety stop, now or ``after_s`` (mid-move).
- ``kill``: the controller process dies: connections reset, ports refuse.
- ``freeze``: the controller hangs or the cable is pulled: nothing is answered or streamed,
  open connections stay open (no FIN), new connections are refused. The nastiest case for a
  client, which then blocks until its own timeouts fire.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Mapping
from typing import Literal

from fakes.ur_controller.tcp import TcpService
from fakes.ur_sim import MotionEngine

Port = Literal["rtde", "script", "dashboard", "primary", "secondary"]


class Faults:
    """The fault switches of one controller: its ports' services, its engine, and how it
    dies (``kill``)."""

    def __init__(self, services: Mapping[Port, TcpService], engine: MotionEngine,
                 kill: Callable[[], None]) -> None:
        self._table = dict(services)
        self._engine = engine
        self._kill = kill
        self.frozen = False
        self._stall_until_s = 0.0

    def _services(self, ports: tuple[Port, ...]) -> list[TcpService]:
        return [self._table[p] for p in ports]

    def drop_connections(self, ports: tuple[Port, ...] = ("rtde", "script", "dashboard",
                                                          "primary", "secondary"),
                         reset: bool = False) -> None:
        for service in self._services(ports):
            service.drop_all(reset)

    def stall_stream(self, duration_s: float) -> None:
        if duration_s < 0:
            raise ValueError("duration_s must be >= 0")
        self._stall_until_s = time.monotonic() + duration_s

    def stream_stalled(self) -> bool:
        return time.monotonic() < self._stall_until_s

    def protective_stop(self, after_s: float = 0.0) -> None:
        self._engine.inject("protective_stop", after_s)

    def emergency_stop(self, after_s: float = 0.0) -> None:
        self._engine.inject("emergency_stop", after_s)

    def release_emergency_stop(self) -> None:
        self._engine.release_emergency_stop()

    def kill(self) -> None:
        """The controller dies: connections reset, nothing listens any more."""
        self._kill()

    def freeze(self) -> None:
        """The controller stops answering without closing anything it has open."""
        self.frozen = True
        for service in self._services(("rtde", "script", "dashboard", "primary", "secondary")):
            service.frozen = True
            service.stop_listening()
