"""Every error leaves the API as ``{"error": {"code", "message"}}`` with a fitting status.

The cell raises typed refusals with an abstract ``kind``; only this module knows HTTP.
Refusals of the request itself (401, 403, 422) are written to the audit log with the route and
the caller, or ``anonymous``; the cell audits its own refusals (409, 503) where it makes them.
"""

from __future__ import annotations

import logging
from typing import Any

from fastapi import FastAPI, Request
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse
from starlette.exceptions import HTTPException as StarletteHTTPException

from api.http.refusals import audit_refusal
from api.http.schemas import ErrorResponse
from api.status import STATUS
from cell.errors import CellError

log = logging.getLogger(__name__)

AUDITED = frozenset({401, 403, 422})
BODY_PARSE_ERROR = "There was an error parsing the body"  # FastAPI's 400 for an unreadable body


def _resp(text: str) -> dict[str, Any]:
    return {"model": ErrorResponse, "description": text}


# Documented on every /api/v1 route, so the OpenAPI schema tells clients what to expect.
ERROR_RESPONSES: dict[int | str, dict[str, Any]] = {
    401: _resp("missing or unknown token (answered before the body is read)"),
    403: _resp("the token's role may not do this"),
    413: _resp("request body larger than the limit (64 KiB)"),
    415: _resp("a request body that is not application/json"),
    422: _resp("malformed request or outside a configured limit (code names which)"),
}
Responses = dict[int | str, dict[str, Any]]
CONFLICT: Responses = {409: _resp("refused in the cell's current state (busy, protective "
                                  "stop, stale pose, target not located, ...); nothing moved")}
UNAVAILABLE: Responses = {503: _resp("a device the request needs is unavailable (camera_lost, "
                          "arm_disconnected)")}
NOT_FOUND: Responses = {404: _resp("no such object (job, taught pose, alarm, image)")}
DEVICE_ERRORS: Responses = {**CONFLICT, **UNAVAILABLE}


def error_body(code: str, message: str) -> dict[str, dict[str, str]]:
    return {"error": {"code": code, "message": message}}


def _validation_message(err: RequestValidationError) -> str:
    parts = []
    for e in err.errors()[:5]:
        loc = ".".join(str(p) for p in e.get("loc", ()) if p != "body")
        parts.append(f"{loc or 'body'}: {e.get('msg', 'invalid')}")
    return "; ".join(parts) or "invalid request"


def _audit(request: Request, status: int, code: str, message: str) -> None:
    caller = getattr(request.state, "caller", None)
    route = getattr(request.scope.get("route"), "path", request.url.path)
    audit_refusal(request.app, caller.label if caller is not None else "anonymous",
                  request.method, route, status, code, message)


def install(app: FastAPI) -> None:
    @app.exception_handler(CellError)
    async def _cell_error(request: Request, err: CellError) -> JSONResponse:
        status = STATUS.get(err.kind, 409)
        headers = {"WWW-Authenticate": "Bearer"} if err.kind == "unauthorized" else None
        if status in (401, 403):  # the cell audits its own 409/422/503 refusals
            _audit(request, status, err.code, err.message)
        return JSONResponse(error_body(err.code, err.message), status, headers=headers)

    @app.exception_handler(RequestValidationError)
    async def _invalid(request: Request, err: RequestValidationError) -> JSONResponse:
        message = _validation_message(err)
        _audit(request, 422, "invalid_request", message)
        return JSONResponse(error_body("invalid_request", message), 422)

    @app.exception_handler(StarletteHTTPException)
    async def _http(request: Request, err: StarletteHTTPException) -> JSONResponse:
        if err.status_code == 400 and err.detail == BODY_PARSE_ERROR:
            # a body the framework could not decode (not UTF-8, ...): malformed, as documented
            message = "body: the request body could not be read as JSON text"
            _audit(request, 422, "invalid_request", message)
            return JSONResponse(error_body("invalid_request", message), 422)
        code = {404: "not_found", 405: "method_not_allowed"}.get(err.status_code, "http_error")
        return JSONResponse(error_body(code, str(err.detail)), err.status_code,
                            headers=getattr(err, "headers", None))

    @app.exception_handler(Exception)
    async def _unexpected(request: Request, err: Exception) -> JSONResponse:
        log.exception("unhandled error on %s %s", request.method, request.url.path)
        return JSONResponse(error_body("internal_error", f"unexpected error: {err!r}"), 500)
