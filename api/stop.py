"""What the routes that must never queue behind other requests share: STOP, status, health,
events.

FastAPI runs a plain ``def`` dependency (as :func:`api.auth.require` is) in the same worker
thread pool as every blocking handler, so under load a STOP waited for a pool thread just to
check its token. These dependencies are ``async``: the token is checked on the event loop in
microseconds. The STOP itself is handed to the cell's stop thread (:mod:`cell.stop`), which
shares nothing with the pool; the handler only awaits its answer. Reads answer from the cell's
snapshot (:mod:`cell.snapshot`), JSON encoded once per refresh.
"""

from __future__ import annotations

import asyncio
from collections.abc import Awaitable, Callable
from typing import Annotated, Any

from fastapi import Depends, Request
from fastapi.security import HTTPAuthorizationCredentials
from starlette.concurrency import run_in_threadpool

from api.auth import QUERY_TOKEN, Caller, authorise, bearer, header_token
from cell.service import Cell
from cell.snapshot import Snap


def require_now(permission: str) -> Callable[..., Awaitable[Caller]]:
    """:func:`api.auth.require` (the Authorization header only), checked on the event loop."""

    async def dependency(
        request: Request,
        credentials: HTTPAuthorizationCredentials | None = Depends(bearer),  # noqa: B008
    ) -> Caller:
        return authorise(request, header_token(request, credentials), permission)

    return dependency


def require_stream_now(permission: str) -> Callable[..., Awaitable[Caller]]:
    """:func:`api.auth.require_stream` (header or ``?token=``), checked on the event loop."""

    async def dependency(
        request: Request,
        credentials: HTTPAuthorizationCredentials | None = Depends(bearer),  # noqa: B008
        token: str | None = QUERY_TOKEN,
    ) -> Caller:
        return authorise(request, credentials.credentials if credentials else token,
                         permission)

    return dependency


ReadNow = Annotated[Caller, Depends(require_now("read"))]
StreamNow = Annotated[Caller, Depends(require_stream_now("read"))]
StopCaller = Annotated[Caller, Depends(require_now("stop"))]


async def stop_now(cell: Cell, caller: str, reason: str) -> dict[str, Any]:
    """Hand the stop to the cell's stop thread and await its answer on the event loop."""
    loop = asyncio.get_running_loop()
    answer: asyncio.Future[dict[str, Any]] = loop.create_future()

    def settle(result: dict[str, Any]) -> None:
        if not answer.done():
            answer.set_result(result)

    def done(result: dict[str, Any]) -> None:
        loop.call_soon_threadsafe(settle, result)

    cell.stopper.submit(caller, reason, done)
    return await answer


async def snapshot_now(cell: Cell) -> Snap:
    """The cell's snapshot without blocking the event loop: the fresh one at once, or (rarely:
    the refresh thread is late, or a motion just ended) refreshed in a worker thread."""
    snap = cell.snapshot.fresh()
    if snap is None:
        snap = await run_in_threadpool(cell.snapshot.current)
    return snap
