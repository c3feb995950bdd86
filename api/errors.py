"""Every error leaves the API as ``{"error": {"code", "message"}}`` with a fitting status.

The cell raises typed refusals with an abstract ``kind``; only this module knows HTTP.
"""

from __future__ import annotations

import logging
from typing import Any

from fastapi import FastAPI, Request
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse
from starlette.exceptions import HTTPException as StarletteHTTPException

from api.schemas import ErrorResponse
from cell.safety import CellError

log = logging.getLogger(__name__)

STATUS = {
    "invalid": 422, "conflict": 409, "unavailable": 503, "not_found": 404,
    "unauthorized": 401, "forbidden": 403,
}

# Documented on every route, so the OpenAPI schema tells clients what to expect.
ERROR_RESPONSES: dict[int | str, dict[str, Any]] = {
    status: {"model": ErrorResponse, "description": text} for status, text in (
        (401, "missing or unknown token"), (403, "the token's role may not do this"),
        (409, "refused in the cell's current state (busy, protective stop, stale pose, ...)"),
        (422, "malformed request or outside a configured limit"),
        (503, "a device the request needs is unavailable (camera lost, arm disconnected)"),
    )
}


class AuthError(CellError):
    kind = "unauthorized"


class ForbiddenError(CellError):
    kind = "forbidden"


def error_body(code: str, message: str) -> dict[str, dict[str, str]]:
    return {"error": {"code": code, "message": message}}


def _validation_message(err: RequestValidationError) -> str:
    parts = []
    for e in err.errors()[:5]:
        loc = ".".join(str(p) for p in e.get("loc", ()) if p != "body")
        parts.append(f"{loc or 'body'}: {e.get('msg', 'invalid')}")
    return "; ".join(parts) or "invalid request"


def install(app: FastAPI) -> None:
    @app.exception_handler(CellError)
    async def _cell_error(request: Request, err: CellError) -> JSONResponse:
        headers = {"WWW-Authenticate": "Bearer"} if err.kind == "unauthorized" else None
        return JSONResponse(error_body(err.code, err.message), STATUS.get(err.kind, 409),
                            headers=headers)

    @app.exception_handler(RequestValidationError)
    async def _invalid(request: Request, err: RequestValidationError) -> JSONResponse:
        return JSONResponse(error_body("invalid_request", _validation_message(err)), 422)

    @app.exception_handler(StarletteHTTPException)
    async def _http(request: Request, err: StarletteHTTPException) -> JSONResponse:
        code = {404: "not_found", 405: "method_not_allowed"}.get(err.status_code, "http_error")
        return JSONResponse(error_body(code, str(err.detail)), err.status_code,
                            headers=getattr(err, "headers", None))

    @app.exception_handler(Exception)
    async def _unexpected(request: Request, err: Exception) -> JSONResponse:
        log.exception("unhandled error on %s %s", request.method, request.url.path)
        return JSONResponse(error_body("internal_error", f"unexpected error: {err!r}"), 500)
