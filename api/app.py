"""``create_app(cell)``: the FastAPI application around one running Cell.

The app does not own the cell's lifetime unless asked (``close_cell_on_shutdown``), so tests
can build a cell, serve it, and inspect it directly.
"""

from __future__ import annotations

import asyncio
import sys
import threading
from collections.abc import AsyncIterator
from contextlib import asynccontextmanager

from fastapi import Depends, FastAPI, Response
from fastapi.responses import PlainTextResponse
from prometheus_client import CONTENT_TYPE_LATEST

from api.auth import TokenTable, require
from api.http import errors, logs, metrics, openapi_limits
from api.http.docs import mount_docs
from api.http.fast_lane import FastLane
from api.http.guard import OPEN_PATHS, RequestGuard
from api.http.live import LiveView
from api.http.page import mount_page
from api.http.request_timer import RequestTimer
from api.http.routes.arm import router as arm_router
from api.http.routes.calibration import router as calibration_router
from api.http.routes.main import router, sim_router
from api.http.routes.ops import router as ops_router
from api.http.routes.pick import router as pick_router
from api.http.routes.recipes import router as recipes_router
from api.http.routes.servo import router as servo_router
from api.plc.interfaces import Interfaces
from cell.config.endpoints import with_ports
from cell.runtime import freeze_startup_objects
from cell.service import Cell

DESCRIPTION = """Vision-guided UR cell: locate the dot target, approach it with look-and-move,
jog, stop, grip, calibrate; alarms, job history and camera settings for the operator page.

- Poses are `{"position_mm": [x, y, z], "rotvec_rad": [rx, ry, rz]}`.
- Errors are `{"error": {"code", "message"}}`; `code` is one of the `ErrorCode` enum.
  401 missing/unknown token (answered before the body is read), 403 role, 404 unknown object,
  409 refused in the current state (nothing moved), 413 body too large, 415 body not JSON,
  422 malformed or outside a limit, 503 a device is unavailable.
- Authorise with `Authorization: Bearer <token>`. Only the GET streaming routes (camera
  frames, event streams) also take `?token=`; it is redacted from the logs.
- `POST /approach` with `wait=true` answers 200 when the job ended, also when it failed or
  was cancelled: read the job's `state` and `error`.
"""


def create_app(cell: Cell, *, close_cell_on_shutdown: bool = False,
               interfaces: bool = False, start_cell: bool = False) -> FastAPI:
    """Build the API for ``cell``. Raises ConfigError when a sample token is configured on
    hardware other than the fakes. ``interfaces``: also serve the configured OPC UA server and
    URScript XML-RPC endpoint (api.plc.interfaces) while the app runs. ``start_cell``: the
    cell is built but not started; the app's start-up starts it, and HTTP serves without
    waiting for the arm's connect and power-on, the gripper's activation or those servers'
    sockets (``/health`` says ``starting`` until they have ended)."""
    tokens = TokenTable(list(cell.config.api.tokens), simulated=cell.hw.simulated)
    logs.install()
    doors = Interfaces(cell)

    @asynccontextmanager
    async def lifespan(app: FastAPI) -> AsyncIterator[None]:
        logs.install()  # uvicorn's handlers exist by now
        if interfaces:
            doors.start_in_background(cell.startup, then=freeze_startup_objects)
        if start_cell:
            try:
                await asyncio.to_thread(cell.start, True)
            except BaseException as err:
                doors.close()  # after their start has ended: nothing is left listening
                if close_cell_on_shutdown:
                    cell.close()
                print(f"error ({getattr(err, 'code', 'startup_failed')}): the cell could not "
                      f"start: {err}", file=sys.stderr)
                raise
            freeze_startup_objects()
        yield
        doors.close()
        app.state.metrics.close()
        if close_cell_on_shutdown:
            cell.close()

    app = FastAPI(title="ur-vision-cell", version="0.2.0", lifespan=lifespan,
                  description=DESCRIPTION, docs_url=None, redoc_url=None)
    app.state.cell = cell
    app.state.tokens = tokens
    app.state.anonymous_stop = bool(getattr(cell.config.api, "anonymous_stop", True))
    app.state.closing = threading.Event()  # set at shutdown: streams end on their own
    app.state.metrics = metrics.Metrics(cell)
    app.state.live = LiveView(cell)
    errors.install(app)
    app.include_router(router)
    app.include_router(arm_router)  # operator recovery: home, unlock, power
    app.include_router(servo_router)  # POST /track
    app.include_router(pick_router)  # POST /pick
    app.include_router(recipes_router)  # recipes (products) and approaches with one
    app.include_router(calibration_router)  # hand-eye routine and taught poses
    app.include_router(ops_router)  # alarms, camera settings, image log
    if cell.sim is not None:
        app.include_router(sim_router)
    app.add_middleware(RequestGuard)
    app.add_middleware(RequestTimer)  # times the guard's refusals too
    app.add_middleware(FastLane)  # outermost: plain /status and /stop skip the rest

    public = bool(getattr(cell.config.api, "metrics_public", False))
    app.state.open_paths = OPEN_PATHS | ({"/api/v1/metrics"} if public else set())
    guard = [] if public else [Depends(require("read"))]
    note = ("No token needed (`[api] metrics_public = true`)." if public else
            "Needs a token of any role (set `[api] metrics_public = true` to scrape "
            "without one).")

    @app.get("/metrics", response_class=PlainTextResponse, tags=["status"],
             dependencies=guard, responses=errors.ERROR_RESPONSES, description=note)
    @app.get("/api/v1/metrics", response_class=PlainTextResponse, tags=["status"],
             dependencies=guard, responses=errors.ERROR_RESPONSES, description=note)
    def prometheus() -> Response:
        """Prometheus text format."""
        return Response(app.state.metrics.render(), media_type=CONTENT_TYPE_LATEST)

    mount_docs(app)
    mount_page(app)
    openapi_limits.install(app, cell.config.limits)
    return app


def app_from_environment() -> FastAPI:
    """uvicorn factory for ``cell serve``: the config named by $CELL_CONFIG (default: the
    built-in simulated cell), its hardware, job store and image log, served; the cell
    starts with the app, beside the PLC servers (``create_app(start_cell=True)``)."""
    import os

    from cell.config.schema import load_config
    from cell.runtime import SHUTDOWN_HOOKS, build_cell

    try:
        config = with_ports(load_config(os.environ.get("CELL_CONFIG") or None),
                            _port_from_environment("CELL_OPCUA_PORT"),
                            _port_from_environment("CELL_XMLRPC_PORT"),
                            _port_from_environment("CELL_MODBUS_PORT"))
        Interfaces.prefetch(config)  # their libraries load while the devices start
        cell = build_cell(config, config_path=os.environ.get("CELL_CONFIG") or None,
                          wait_ready=False, stall_traces=True)
    except Exception as err:  # a clear line instead of a traceback from inside uvicorn
        code = getattr(err, "code", "startup_failed")
        print(f"error ({code}): the cell could not start: {err}", file=sys.stderr)
        raise SystemExit(2) from err
    try:
        app = create_app(cell, close_cell_on_shutdown=True, interfaces=True, start_cell=True)
    except BaseException:
        cell.close()
        raise

    def on_signal() -> None:
        app.state.closing.set()
        cell.stop("service", reason="shutdown: the service is stopping")

    SHUTDOWN_HOOKS.append(on_signal)  # cell serve runs it on SIGTERM, before the HTTP drain
    return app


def _port_from_environment(name: str) -> int | None:
    """A port ``cell serve`` passed on (``--opcua-port``, ``--xmlrpc-port``), else None."""
    import os

    value = os.environ.get(name)
    return int(value) if value else None
