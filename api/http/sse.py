"""Server-sent events from a cell event subscription (one implementation for every stream).

A stream waits for its subscription's events (the bus wakes its event loop), it does not
poll; a client that stops reading only fills its own bounded queue (the oldest events are
dropped) and blocks only its own stream.
"""

from __future__ import annotations

import asyncio
import json
from collections.abc import AsyncIterator, Callable
from typing import Any

from fastapi import Request
from fastapi.responses import StreamingResponse

from cell.jobs.events import Subscription

WAKE_S = 0.5  # an idle stream checks for shutdown and a gone client this often
KEEPALIVE_S = 5.0  # a comment line this often keeps proxies from closing an idle stream

SSE_RESPONSES: dict[int | str, dict[str, Any]] = {
    200: {"content": {"text/event-stream": {}}, "description": "server-sent events"},
}


def sse_response(request: Request, sub: Subscription, max_events: int | None,
                 keep: Callable[[dict[str, Any]], bool] = lambda ev: True) -> StreamingResponse:
    """Stream the subscription's events (those ``keep`` accepts) until the client leaves or
    ``max_events`` were sent; the subscription is closed either way."""

    closing = getattr(request.app.state, "closing", None)

    async def stream() -> AsyncIterator[str]:
        loop = asyncio.get_running_loop()
        wake = asyncio.Event()

        def notify() -> None:
            loop.call_soon_threadsafe(wake.set)

        sub.notify = notify
        sent = 0
        idle_s = 0.0
        try:
            yield "retry: 1000\n\n"
            while max_events is None or sent < max_events:
                if closing is not None and closing.is_set():
                    break  # the service is stopping: do not hold its shutdown up
                ev = sub.get(0)
                if ev is None:
                    # wait for the bus to wake us (no polling); look at the closing flag
                    # and the client every WAKE_S meanwhile
                    wake.clear()
                    if sub.queue.empty():
                        try:
                            await asyncio.wait_for(wake.wait(), WAKE_S)
                        except TimeoutError:
                            idle_s += WAKE_S
                            if await request.is_disconnected():
                                break
                            if idle_s >= KEEPALIVE_S:
                                idle_s = 0.0
                                yield ": keep-alive\n\n"
                    continue
                if not keep(ev):
                    continue
                idle_s = 0.0
                sent += 1
                yield f"event: {ev['type']}\ndata: {json.dumps(ev)}\n\n"
        finally:
            sub.notify = None
            sub.close()

    return StreamingResponse(stream(), media_type="text/event-stream",
                             headers={"Cache-Control": "no-store"})
