"""What the routes that must never queue behind other requests share: STOP, status, health,
events.

FastAPI runs a plain ``def`` dependency (as :func:`api.auth.require` is) in the same worker
thread pool as every blocking handler, so under load a STOP waited for a pool thread just to
check its token. These dependencies are ``async``: the token is checked on the event loop in
microseconds. The STOP itself is handed to the cell's stop thread (:mod:`cell.actions.stop`), which
shares nothing with the pool; the handler only awaits its answer. Reads answer from the cell's
snapshot (:mod:`cell.supervision.snapshot`), JSON encoded once per refresh.
"""

from __future__ import annotations

import asyncio
from typing import Annotated, Any

from fastapi import Depends
from starlette.concurrency import run_in_threadpool

from api.auth import Caller, Read, Stream, require_stop
from cell.service import Cell
from cell.supervision.snapshot import Snap

# Aliases kept for the routes that must never queue: api.auth's dependencies are async.
ReadNow = Read
StreamNow = Stream
# Any valid token, or none at all when ``[api] anonymous_stop`` is on (api.auth.require_stop).
StopCaller = Annotated[Caller, Depends(require_stop())]


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
