"""The service's other doors, next to HTTP: the OPC UA server, the URScript XML-RPC endpoint
and the Modbus TCP server.

``cell serve`` starts them with the app (``create_app(cell, interfaces=True)``), behind an HTTP
API that already answers (``/health`` says ``starting`` until they listen), and stops them
before the cell closes. One that cannot listen (its port is taken) is logged and left out; the
HTTP API and the other still serve, because a PLC port in use must not keep the operator page
(and its STOP) away.
"""

from __future__ import annotations

import importlib
import logging
import threading
from collections.abc import Callable
from typing import Protocol

from cell.config.endpoints import opcua_cert_dir
from cell.config.schema import CellConfig
from cell.service import Cell
from cell.supervision.startup import Startup

log = logging.getLogger(__name__)
STARTUP_PART = "PLC servers"
STARTER_JOIN_S = 30.0
TITLES = {"opcua": "the OPC UA server", "xmlrpc": "the URScript XML-RPC endpoint",
          "modbus": "the Modbus TCP server"}


class _Server(Protocol):
    def start(self) -> None: ...
    def close(self) -> None: ...


class Interfaces:
    """Starts and stops the configured OPC UA and XML-RPC servers around one cell."""

    def __init__(self, cell: Cell) -> None:
        self.cell = cell
        self.running: dict[str, _Server] = {}
        self.failed: dict[str, str] = {}  # server -> why it does not serve
        self._starter: threading.Thread | None = None
        cell.health_reasons.append(self.reasons)

    @staticmethod
    def prefetch(config: CellConfig) -> threading.Thread:
        """Import the configured servers' modules in a thread of their own (asyncua and
        pymodbus take about a second), while the caller builds the cell, whose start mostly
        waits on devices; :meth:`start` then finds them loaded. A failed import is left for
        :meth:`start` to report."""
        names = [name for name, on in (("api.plc.opcua", config.opcua.enabled),
                                       ("api.plc.xmlrpc", bool(config.urscript.xmlrpc_port)),
                                       ("api.plc.modbus", bool(config.modbus.port))) if on]

        def load() -> None:
            for name in names:
                try:
                    importlib.import_module(name)
                except Exception:  # start() imports it again and says why
                    return

        thread = threading.Thread(target=load, name="doors-prefetch", daemon=True)
        thread.start()
        return thread

    def start(self) -> None:
        config = self.cell.config
        if config.opcua.enabled:
            from api.plc.opcua import OpcUaServer

            self._start("opcua", config.opcua.endpoint,
                        OpcUaServer(self.cell, config.opcua, opcua_cert_dir(config)))
        if config.urscript.xmlrpc_port:
            from api.plc.xmlrpc import XmlRpcServer

            self._start("xmlrpc", f"{config.urscript.host}:{config.urscript.xmlrpc_port}",
                        XmlRpcServer(self.cell, config.urscript))
        if config.modbus.port:
            from api.plc.modbus import ModbusServer

            self._start("modbus", f"{config.modbus.host}:{config.modbus.port}",
                        ModbusServer(self.cell, config.modbus))

    def start_in_background(self, startup: Startup,
                            then: Callable[[], None] = lambda: None) -> None:
        """:meth:`start` in a thread of its own (the servers' imports and listening sockets
        take about half a second); ``startup`` holds a part of the start until it has ended,
        and ``then`` runs after it."""
        startup.begin(STARTUP_PART)

        def run() -> None:
            try:
                self.start()
                then()
            except Exception:  # each server's own failure is reported by _start
                log.exception("starting the PLC servers failed")
            finally:
                startup.end(STARTUP_PART)

        self._starter = threading.Thread(target=run, name="doors-start", daemon=True)
        self._starter.start()

    def _start(self, name: str, where: str, server: _Server) -> None:
        try:
            server.start()
        except Exception as err:  # a port in use, a bad certificate file, ...
            log.error("%s: cannot serve on %s: %s; the rest of the service runs without it",
                      name, where, err)
            self.failed[name] = f"{TITLES[name]} cannot serve on {where}: {err}"
            server.close()
            return
        self.running[name] = server

    def reasons(self) -> list[dict[str, str]]:
        """``/health`` reasons: each configured server that could not start."""
        return [{"code": "plc_server_down",
                 "message": f"{why}; PLCs cannot reach the cell through it (restart the "
                            "service once the cause is fixed)"}
                for why in list(self.failed.values())]

    def close(self) -> None:
        if self._starter is not None:  # a server half-started would be left listening
            self._starter.join(timeout=STARTER_JOIN_S)
        for name, server in list(self.running.items()):
            try:
                server.close()
            except Exception:
                log.exception("closing %s failed", name)
        self.running.clear()
