"""The gate in front of every ``/api/v1`` route: authenticate first, then look at the body.

Order matters: a request without a valid token is answered 401
before a byte of its body is read or parsed, so an anonymous client cannot make the service
parse 10 MB bodies; bodies are capped (413) and must be ``application/json`` (415), so a
cross-site "simple" form POST never reaches a route, and UTF-8 (422 ``invalid_request``, as
any malformed body). Refusals are written to the audit log with
the path and the caller (``anonymous`` when there is none). The one request taken without a
token is a STOP with no credential at all, when ``[api] anonymous_stop`` is on
(:func:`api.auth.anonymous_stop_caller`); its body is checked as every other.
"""

from __future__ import annotations

import json
import logging
from typing import Any

from starlette.types import ASGIApp, Message, Receive, Scope, Send

from api.auth import anonymous_stop_caller, bearer_of
from api.http.errors import error_body
from api.http.refusals import audit_refusal
from cell.errors import CellError

log = logging.getLogger(__name__)

MAX_BODY_BYTES = 64 * 1024  # the largest real body (a jog or an approach) is under 1 KB
OPEN_PATHS = frozenset({"/api/v1/health"})
STOP_PATH = "/api/v1/stop"  # with ``[api] anonymous_stop``, also taken without a token
BODY_METHODS = frozenset({"POST", "PUT", "PATCH", "DELETE"})


class RequestGuard:
    """Pure ASGI middleware (it must run before FastAPI reads the body)."""

    def __init__(self, app: ASGIApp, max_body_bytes: int = MAX_BODY_BYTES) -> None:
        self.app = app
        self.max_body_bytes = max_body_bytes

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        path = scope.get("path", "")
        app: Any = scope.get("app")
        open_paths = getattr(getattr(app, "state", None), "open_paths", OPEN_PATHS)
        if scope["type"] != "http" or not path.startswith("/api/v1/") or path in open_paths:
            await self.app(scope, receive, send)
            return
        method = scope["method"]
        headers = {k.decode("latin-1").lower(): v.decode("latin-1")
                   for k, v in scope.get("headers", [])}
        token = bearer_of(headers.get("authorization", ""))
        if token is None and method in ("GET", "HEAD"):
            token = _query_token(scope)  # the routes decide whether they accept it
        try:
            caller = anonymous_stop_caller(scope) if method == "POST" and path == STOP_PATH \
                else None
            if caller is None:
                caller = app.state.tokens.lookup(token)
        except CellError as err:
            await self._refuse(scope, send, 401, err.code, err.message, "anonymous",
                               {"WWW-Authenticate": "Bearer"})
            return
        label = caller.label
        if method not in BODY_METHODS:
            await self.app(scope, receive, send)
            return
        length = headers.get("content-length")
        if length is not None and (not length.isdigit() or int(length) > self.max_body_bytes):
            await self._refuse(scope, send, 413, "body_too_large", f"request bodies are "
                               f"limited to {self.max_body_bytes} bytes", label)
            return
        ctype = headers.get("content-type", "").split(";")[0].strip().lower()
        if ctype and ctype != "application/json":
            await self._refuse(scope, send, 415, "unsupported_media_type",
                               f"bodies must be application/json, not {ctype!r}", label)
            return
        body = b""
        more = True
        while more:
            message = await receive()
            if message["type"] == "http.disconnect":
                return
            body += message.get("body", b"")
            more = message.get("more_body", False)
            if len(body) > self.max_body_bytes:
                await self._refuse(scope, send, 413, "body_too_large", f"request bodies are "
                                   f"limited to {self.max_body_bytes} bytes", label)
                return
        if body and not ctype:
            await self._refuse(scope, send, 415, "unsupported_media_type",
                               "a request body needs Content-Type: application/json", label)
            return
        problem = _not_utf8(body)
        if problem is not None:  # JSON is UTF-8 (RFC 8259); the framework would answer 400
            await self._refuse(scope, send, 422, "invalid_request", problem, label)
            return
        replayed = False

        async def replay() -> Message:
            nonlocal replayed
            if not replayed:
                replayed = True
                return {"type": "http.request", "body": body, "more_body": False}
            return await receive()

        await self.app(scope, replay, send)

    @staticmethod
    async def _refuse(scope: Scope, send: Send, status: int, code: str, message: str,
                      caller: str, headers: dict[str, str] | None = None) -> None:
        audit_refusal(scope["app"], caller, scope["method"], scope.get("path", ""), status,
                      code, message)
        payload = json.dumps(error_body(code, message)).encode()
        raw = [(b"content-type", b"application/json"),
               (b"content-length", str(len(payload)).encode())]
        raw += [(k.lower().encode(), v.encode()) for k, v in (headers or {}).items()]
        await send({"type": "http.response.start", "status": status, "headers": raw})
        await send({"type": "http.response.body", "body": payload})


def _not_utf8(body: bytes) -> str | None:
    """Why ``body`` is not UTF-8 text, or None when it is (or is empty)."""
    try:
        body.decode("utf-8")
    except UnicodeDecodeError as err:
        return f"body: the request body is not valid UTF-8 (byte {err.start}: {err.reason})"
    return None


def _query_token(scope: Scope) -> str | None:
    from urllib.parse import parse_qs

    values = parse_qs(scope.get("query_string", b"").decode("latin-1")).get("token")
    return values[0] if values else None
