"""Per-route request latency for ``cell_http_request_duration_seconds``, as pure ASGI.

Starlette's ``BaseHTTPMiddleware`` (``@app.middleware("http")``) runs every request in an
extra task and copies every body chunk through a memory stream: under the service benchmark's
load (200 status reads and 300 SSE events a second) that was about a third of the event
loop's CPU, the loop that also answers STOP. This one only wraps ``send``.

The time observed is from the request to its response headers, so a stream (SSE, MJPEG)
counts its time to start, not how long the client watched.
"""

from __future__ import annotations

import time
from typing import Any

from starlette.types import ASGIApp, Message, Receive, Scope, Send


class RequestTimer:
    """Observes ``(method, route template, status, seconds)`` into the app's metrics."""

    def __init__(self, app: ASGIApp) -> None:
        self.app = app

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        t0 = time.perf_counter()
        observed = False

        def observe(status: int) -> None:
            nonlocal observed
            if observed:
                return
            observed = True
            route = scope.get("route")
            app: Any = scope.get("app")
            app.state.metrics.observe_http(scope["method"], getattr(route, "path", "unmatched"),
                                           status, time.perf_counter() - t0)

        async def timed_send(message: Message) -> None:
            if message["type"] == "http.response.start":
                observe(int(message["status"]))
            await send(message)

        try:
            await self.app(scope, receive, timed_send)
        except BaseException:
            observe(500)
            raise
