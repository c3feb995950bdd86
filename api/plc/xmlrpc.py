"""The URScript XML-RPC endpoint, configured by ``[urscript]`` (off while ``xmlrpc_port`` is 0).

A PolyScope program asks the cell with ``rpc = rpc_factory("xmlrpc", "http://HOST:PORT/RPC2")``
(``/<token>/RPC2`` when ``require_token``):

- ``locate()``: the target's base-frame pose as a UR pose (a struct x, y, z, rx, ry, rz in m and
  rad, which URScript reads as ``p[...]``);
- ``approach_pose(standoff_mm)`` and ``taught_pose(name, standoff_mm=0)``: the TCP goal for the
  program's own ``movel`` (robot-program-driven mode: the cell locates but never moves the arm);
- ``recipe_pose(recipe, standoff_mm=-1)``: the same for a recipe's first target (its name or
  number; its dot layout, taught pose and, for a negative standoff, its standoff);
- ``status()``: the cell's state (``idle``, ``approach``, ``protective_stop``, ...);
- ``try_locate()``, ``try_approach_pose(standoff_mm)``, ``try_taught_pose(name, standoff_mm=0)``:
  the same as a list ``[status, x, y, z, rx, ry, rz]`` (status 0, or the fault code the plain
  call would give, with zeros), for a program that handles a refusal itself.

A refusal is an XML-RPC fault whose code is the HTTP status the API would answer (403, 409,
422, 503) and whose string starts with the cell's error code (``"stale_pose: ..."``); a malformed
request is a fault too and the endpoint keeps serving. Every command is in the audit log with
the caller ``xmlrpc:<name>(<role>)``. Standard library server (one thread per request).
"""

from __future__ import annotations

import inspect
import logging
import socketserver
import threading
from collections.abc import Callable
from typing import Any
from xmlrpc.client import Fault
from xmlrpc.server import SimpleXMLRPCRequestHandler, SimpleXMLRPCServer

import numpy as np
from numpy.typing import NDArray

from api import remote
from api.remote import RemoteCaller
from cell.config.schema import UrscriptConfig
from cell.error_codes import ErrorCode
from cell.errors import CellError, ForbiddenError
from cell.service import Cell

log = logging.getLogger(__name__)

RPC_PATH = "/RPC2"
FAULT_UNKNOWN_METHOD = 404
FAULT_BAD_ARGUMENTS = 422
FAULT_INTERNAL = 500


def ur_struct(T_base: NDArray[np.float64]) -> dict[str, float]:
    """A UR pose as XML-RPC carries it to URScript: a struct x, y, z (m), rx, ry, rz (rad)."""
    return dict(zip(("x", "y", "z", "rx", "ry", "rz"), remote.ur_pose(T_base), strict=True))


class _Methods:
    """What a robot program may call; each takes the caller first."""

    def __init__(self, cell: Cell) -> None:
        self.cell = cell

    def locate(self, caller: RemoteCaller) -> dict[str, float]:
        return ur_struct(remote.locate(self.cell, caller).T_base_target)

    def approach_pose(self, caller: RemoteCaller, standoff_mm: float) -> dict[str, float]:
        goal, _ = remote.tcp_goal(self.cell, caller, "approach_pose", standoff_mm=standoff_mm)
        return ur_struct(goal)

    def taught_pose(self, caller: RemoteCaller, name: str,
                    standoff_mm: float = 0.0) -> dict[str, float]:
        goal, _ = remote.tcp_goal(self.cell, caller, "taught_pose", standoff_mm=standoff_mm,
                                  taught=name)
        return ur_struct(goal)

    def recipe_pose(self, caller: RemoteCaller, recipe: str | int,
                    standoff_mm: float = -1.0) -> dict[str, float]:
        return ur_struct(self._recipe_goal(caller, recipe, standoff_mm))

    def _recipe_goal(self, caller: RemoteCaller, recipe: str | int,
                     standoff_mm: float) -> NDArray[np.float64]:
        remote.require(self.cell, caller, "locate", "recipe_pose", {"recipe": recipe})
        with remote.recipe_selected(self.cell, remote.recipe_ref(recipe)) as (_, target):
            standoff = target.standoff_mm if isinstance(standoff_mm, int | float) \
                and not isinstance(standoff_mm, bool) and standoff_mm < 0 else standoff_mm
            goal, _ = remote.tcp_goal(self.cell, caller, "recipe_pose", standoff_mm=standoff,
                                      taught=target.taught or None)
        return goal

    def try_locate(self, caller: RemoteCaller) -> list[float]:
        return self._tried(lambda: remote.locate(self.cell, caller).T_base_target)

    def try_approach_pose(self, caller: RemoteCaller, standoff_mm: float) -> list[float]:
        return self._tried(lambda: remote.tcp_goal(
            self.cell, caller, "approach_pose", standoff_mm=standoff_mm)[0])

    def try_taught_pose(self, caller: RemoteCaller, name: str,
                        standoff_mm: float = 0.0) -> list[float]:
        return self._tried(lambda: remote.tcp_goal(
            self.cell, caller, "taught_pose", standoff_mm=standoff_mm, taught=name)[0])

    @staticmethod
    def _tried(work: Callable[[], NDArray[np.float64]]) -> list[float]:
        """``[status, x, y, z, rx, ry, rz]``: status 0 and the pose, or the fault code the
        plain call would raise and zeros. All numbers, so URScript can branch on ``r[0]``
        where a fault would end the program."""
        try:
            return [0.0, *remote.ur_pose(work())]
        except CellError as err:
            return [float(remote.http_status(err))] + [0.0] * 6

    def status(self, caller: RemoteCaller) -> str:
        if not caller.may("read"):
            raise ForbiddenError(ErrorCode.forbidden, f"role {caller.role!r} may not read")
        return str(self.cell.status().get("state", "unknown"))

    def table(self) -> dict[str, Callable[..., Any]]:
        return {"locate": self.locate, "approach_pose": self.approach_pose,
                "taught_pose": self.taught_pose, "try_locate": self.try_locate,
                "try_approach_pose": self.try_approach_pose,
                "try_taught_pose": self.try_taught_pose, "recipe_pose": self.recipe_pose,
                "status": self.status}


class _Handler(SimpleXMLRPCRequestHandler):
    """Finds the caller from the URL path, then dispatches with it."""

    server: _Server
    caller: RemoteCaller | None = None

    def is_rpc_path_valid(self) -> bool:
        self.caller = self.server.caller_for(self.path)
        return self.caller is not None

    def _dispatch(self, method: str, params: tuple[Any, ...]) -> Any:
        assert self.caller is not None  # do_POST checked the path first
        func = self.server.methods.get(method)
        if func is None:
            raise Fault(FAULT_UNKNOWN_METHOD,
                        f"unknown_method: {method!r}; methods: {', '.join(self.server.methods)}")
        try:
            inspect.signature(func).bind(self.caller, *params)
        except TypeError as err:
            raise Fault(FAULT_BAD_ARGUMENTS, f"invalid_request: {method}: {err}") from err
        try:
            return func(self.caller, *params)
        except CellError as err:
            raise Fault(remote.http_status(err), f"{err.code}: {err.message}") from err
        except Exception as err:
            log.exception("XML-RPC %s failed", method)
            raise Fault(FAULT_INTERNAL, f"internal_error: {err!r}") from err

    def log_message(self, format: str, *args: Any) -> None:
        log.debug("xmlrpc %s " + format, self.address_string(), *args)


class _Server(socketserver.ThreadingMixIn, SimpleXMLRPCServer):
    daemon_threads = True
    allow_reuse_address = True

    def __init__(self, cell: Cell, config: UrscriptConfig) -> None:
        self.cell = cell
        self.config = config
        self.methods = _Methods(cell).table()
        self.tokens = {t.token: (t.name or t.role, t.role) for t in cell.config.api.tokens}
        super().__init__((config.host, config.xmlrpc_port), requestHandler=_Handler,
                         allow_none=False, logRequests=False)

    def caller_for(self, path: str) -> RemoteCaller | None:
        """``/RPC2`` (without ``require_token``) or ``/<token>/RPC2``; None: 404."""
        path = path.split("?", 1)[0].rstrip("/")
        if path == RPC_PATH and not self.config.require_token:
            return RemoteCaller("xmlrpc", "urscript", "plc")
        head, _, tail = path.lstrip("/").partition("/")
        if "/" + tail == RPC_PATH and head in self.tokens:
            name, role = self.tokens[head]
            return RemoteCaller("xmlrpc", name, role)
        return None


class XmlRpcServer:
    """``start()`` listens (OSError when the port is taken), ``close()``."""

    def __init__(self, cell: Cell, config: UrscriptConfig) -> None:
        self.cell = cell
        self.config = config
        self._server: _Server | None = None
        self._thread: threading.Thread | None = None

    @property
    def url(self) -> str:
        port = self._server.server_address[1] if self._server else self.config.xmlrpc_port
        path = "/<token>" + RPC_PATH if self.config.require_token else RPC_PATH
        return f"http://{self.config.host}:{port}{path}"

    def start(self) -> None:
        self._server = _Server(self.cell, self.config)
        self._thread = threading.Thread(target=self._server.serve_forever, name="xmlrpc",
                                        kwargs={"poll_interval": 0.2}, daemon=True)
        self._thread.start()

    def close(self) -> None:
        if self._server is not None:
            self._server.shutdown()
            self._server.server_close()
        if self._thread is not None:
            self._thread.join(timeout=5.0)
