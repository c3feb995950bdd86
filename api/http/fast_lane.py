"""The two routes every client hits hardest, answered before the framework's route handling.

``GET /api/v1/status`` (every page and PLC polls it) and ``POST /api/v1/stop`` (it must cut
through any load) cost little themselves: a snapshot's bytes, a hand-over to the stop thread.
Under the service benchmark's load (200 status reads a second beside 300 SSE events) most of
the event loop's time went to what surrounds them in FastAPI: exception and body-limit
middleware, route matching over ~80 routes, dependency solving, response validation. This
middleware answers a well-formed request of either route directly.

Only the plain case: a bearer token that is valid and allowed (for STOP also none at all, with
``[api] anonymous_stop``), no query string, and for STOP
an ``application/json`` body that validates as :class:`api.http.schemas.StopRequest` (or none).
Anything else, every refusal above all, goes on to the regular route unchanged (the body is
replayed), so its error answers, audit rows and documentation stay where they are.
"""

from __future__ import annotations

import time
from typing import Any

from pydantic import ValidationError
from starlette.types import ASGIApp, Message, Receive, Scope, Send

from api.auth import anonymous_stop_caller, bearer_of
from api.http.guard import MAX_BODY_BYTES
from api.http.schemas import StopRequest, StopResult
from api.http.stop import snapshot_now, stop_now
from cell.errors import CellError
from cell.supervision.snapshot import with_age

STATUS_PATH = "/api/v1/status"
STOP_PATH = "/api/v1/stop"
_JSON = (b"content-type", b"application/json")


class FastLane:
    """Pure ASGI: ``/status`` and ``/stop`` when plain, everything else to ``app``."""

    def __init__(self, app: ASGIApp) -> None:
        self.app = app

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] == "http" and not scope.get("query_string"):
            path, method = scope["path"], scope["method"]
            if path == STATUS_PATH and method == "GET":
                if await self._status(scope, send):
                    return
            elif path == STOP_PATH and method == "POST":
                replay = await self._stop(scope, receive, send)
                if replay is None:
                    return
                receive = replay
        await self.app(scope, receive, send)

    async def _status(self, scope: Scope, send: Send) -> bool:
        t0 = time.perf_counter()
        app: Any = scope["app"]
        if _caller(scope, app, "read") is None:
            return False
        snap = await snapshot_now(app.state.cell)
        body = with_age(snap.status_json, snap.age_s())
        await _answer(send, body, (b"cache-control", b"no-store"))
        app.state.metrics.observe_http("GET", STATUS_PATH, 200, time.perf_counter() - t0)
        return True

    async def _stop(self, scope: Scope, receive: Receive, send: Send) -> Receive | None:
        """None when answered, else the ``receive`` that replays what was read."""
        t0 = time.perf_counter()
        app: Any = scope["app"]
        headers = dict(scope.get("headers", []))
        body, more = b"", True
        length = headers.get(b"content-length", b"0")
        ctype = headers.get(b"content-type", b"").split(b";")[0].strip().lower()
        plain = length.isdigit() and int(length) <= MAX_BODY_BYTES and (
            ctype == b"application/json" or (not ctype and length == b"0"))
        while plain and more:
            message = await receive()
            if message["type"] != "http.request":
                return _replay([message], receive)
            body += message.get("body", b"")
            more = message.get("more_body", False)
            plain = len(body) <= MAX_BODY_BYTES
        if body and ctype != b"application/json":
            plain = False  # a body needs its content type (the guard answers 415)
        caller = (_caller(scope, app, "stop") or _anonymous(scope)) if plain else None
        request: StopRequest | None = None
        if caller is not None:
            try:
                request = StopRequest.model_validate_json(body) if body else StopRequest()
            except ValidationError:
                request = None
        if caller is None or request is None:
            consumed: list[Message] = [{"type": "http.request", "body": body, "more_body": more}]
            return _replay(consumed, receive) if body or not more else receive
        out = await stop_now(app.state.cell, caller.label, request.reason)
        app.state.metrics.stop.observe(time.perf_counter() - t0)
        await _answer(send, StopResult.model_validate(out).model_dump_json().encode())
        app.state.metrics.observe_http("POST", STOP_PATH, 200, time.perf_counter() - t0)
        return None


def _caller(scope: Scope, app: Any, permission: str) -> Any | None:
    """The caller of a valid bearer token that has ``permission``, else None."""
    for key, value in scope.get("headers", []):
        if key == b"authorization":
            token = bearer_of(value.decode("latin-1"))
            if token is None:
                return None
            try:
                caller = app.state.tokens.lookup(token)
            except CellError:
                return None
            return caller if permission in caller.permissions else None
    return None


def _anonymous(scope: Scope) -> Any | None:
    """The anonymous caller of a STOP without any credential, else None (a refusal is the
    regular route's to answer)."""
    try:
        return anonymous_stop_caller(scope)
    except CellError:
        return None


async def _answer(send: Send, body: bytes, *extra: tuple[bytes, bytes]) -> None:
    await send({"type": "http.response.start", "status": 200,
                "headers": [_JSON, (b"content-length", str(len(body)).encode()), *extra]})
    await send({"type": "http.response.body", "body": body})


def _replay(messages: list[Message], receive: Receive) -> Receive:
    pending = list(messages)

    async def replayed() -> Message:
        return pending.pop(0) if pending else await receive()

    return replayed

