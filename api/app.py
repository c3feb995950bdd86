"""``create_app(cell)``: the FastAPI application around one running Cell.

The app does not own the cell's lifetime unless asked (``close_cell_on_shutdown``), so tests
can build a cell, serve it, and inspect it directly.
"""

from __future__ import annotations

import threading
import time
from collections.abc import AsyncIterator, Awaitable, Callable
from contextlib import asynccontextmanager

from fastapi import Depends, FastAPI, Request, Response
from fastapi.responses import PlainTextResponse

from api import errors, metrics
from api.auth import TokenTable, require
from api.page import mount_page
from api.routes import router, sim_router
from api.routes_arm import router as arm_router
from api.routes_calibration import install as install_calibration
from api.routes_servo import router as servo_router
from cell.service import Cell

# Called first thing on SIGTERM/SIGINT by ``cell serve`` (see cell.commands.serve), before
# uvicorn waits for open connections: the arm must not wait for an SSE client to leave.
SHUTDOWN_HOOKS: list[Callable[[], None]] = []


def create_app(cell: Cell, *, close_cell_on_shutdown: bool = False) -> FastAPI:
    """Build the API for ``cell``. Raises ConfigError when a sample token is configured on
    hardware other than the fakes."""
    tokens = TokenTable(list(cell.config.api.tokens), simulated=cell.hw.simulated)

    @asynccontextmanager
    async def lifespan(app: FastAPI) -> AsyncIterator[None]:
        yield
        if close_cell_on_shutdown:
            cell.close()

    app = FastAPI(
        title="ur-vision-cell", version="0.1.0", lifespan=lifespan,
        description="Vision-guided UR cell: locate the dot target, approach it with "
        "look-and-move, jog, stop, grip. Poses are {position_mm, rotvec_rad}; errors are "
        '{"error": {"code", "message"}}. Authorise with a bearer token.')
    app.state.cell = cell
    app.state.tokens = tokens
    app.state.closing = threading.Event()  # set at shutdown: streams end on their own
    app.state.http_stats = metrics.HttpStats()
    errors.install(app)
    app.include_router(router)
    app.include_router(arm_router)  # operator recovery: home, unlock, power
    app.include_router(servo_router)  # POST /track (issue 15)
    install_calibration(app)  # hand-eye routine and taught poses (issue 7)
    if cell.sim is not None:
        app.include_router(sim_router)

    @app.middleware("http")
    async def _count(request: Request,
                     call_next: Callable[[Request], Awaitable[Response]]) -> Response:
        t0 = time.perf_counter()
        response = await call_next(request)
        route = request.scope.get("route")
        path = getattr(route, "path", "unmatched")
        app.state.http_stats.observe(request.method, path, response.status_code,
                                     time.perf_counter() - t0)
        return response

    @app.get("/metrics", response_class=PlainTextResponse, tags=["status"],
             dependencies=[Depends(require("read"))], responses=errors.ERROR_RESPONSES)
    @app.get("/api/v1/metrics", response_class=PlainTextResponse, tags=["status"],
             dependencies=[Depends(require("read"))], responses=errors.ERROR_RESPONSES)
    def prometheus() -> str:
        """Prometheus text format."""
        return metrics.render(cell, app.state.http_stats)

    mount_page(app)
    return app


def app_from_environment() -> FastAPI:
    """uvicorn factory for ``cell serve``: the config named by $CELL_CONFIG (default: the
    built-in simulated cell), its hardware, job store and image log, started and served."""
    import os
    import sys

    from cell.runtime import start_cell

    try:
        cell = start_cell(os.environ.get("CELL_CONFIG") or None)
    except Exception as err:  # a clear line instead of a traceback from inside uvicorn
        code = getattr(err, "code", "startup_failed")
        print(f"error ({code}): the cell could not start: {err}", file=sys.stderr)
        raise SystemExit(2) from err
    try:
        app = create_app(cell, close_cell_on_shutdown=True)
    except BaseException:
        cell.close()
        raise

    def on_signal() -> None:
        app.state.closing.set()
        cell.stop("service", reason="shutdown: the service is stopping")

    SHUTDOWN_HOOKS.append(on_signal)
    return app
