"""Bearer tokens from config, each with a role; routes ask for a permission, not a role.

Credentials come from the ``Authorization`` header. Only the GET streaming routes (camera
frames, event streams) also accept ``?token=``, because browsers cannot set headers on
``<img>`` and ``EventSource``; such URLs are redacted from every log line (api.http.logs). A token
in the query of any other route, POST above all, is refused: a cross-site page can make a
browser send a "simple" POST with a URL of its choosing, never with an Authorization header.

Tokens are compared in constant time (``secrets.compare_digest``) against every configured
token, so timing tells nothing about which or how much of one matched. A config may store a
token as ``sha256`` = hex(sha256(salt + token)) with its ``salt`` instead of in the clear.
"""

from __future__ import annotations

import hashlib
import secrets
from collections.abc import Awaitable, Callable
from dataclasses import dataclass
from typing import Annotated, Any
from urllib.parse import parse_qs

from fastapi import Depends, Query, Request
from fastapi.security import HTTPAuthorizationCredentials, HTTPBearer

from cell.config.schema import SAMPLE_TOKENS, ConfigError
from cell.error_codes import ErrorCode
from cell.errors import AuthError, ForbiddenError

# What each permission allows, on every door (HTTP, OPC UA, Modbus, XML-RPC); docs/plc.md has
# the table of permissions by role and the role each door runs as.
#   read          status, jobs, audit, recipes, taught poses, camera frames
#   locate        locate the target (and a program's TCP goal over XML-RPC)
#   approach      approach (with or without a recipe), prepare a recipe, automatic mode
#   track         track the target (servo)
#   home          the joint move to [robot] home_joints_deg
#   gripper       open, close or move the gripper
#   pick          reserved for the pick job (no door uses it yet)
#   jog           jog the arm
#   recover       unlock a protective stop, power on / off, reset the Machine Vision state
#   teach         teach or delete a taught pose
#   calibrate     run the hand-eye routine and apply its result; record the calibration reference
#   check_calibration  check the calibration against the recorded reference
#   edit_recipes  save or delete a recipe
#   camera        change the camera's settings
#   alarm_ack     acknowledge alarms
#   sim_write     move the simulated target (simulated cells only)
# A PLC runs production cycles (locate, approach, track, home, gripper, pick); what wants a
# person at the cell (jogging, unlocking, power) or changes what later jobs do (teaching,
# calibration, recipes, camera settings) stays the operator's.
PRODUCTION = frozenset({"read", "locate", "approach", "track", "home", "gripper", "pick",
                        "check_calibration"})
PERMISSIONS: dict[str, frozenset[str]] = {
    "viewer": frozenset({"read"}),
    "operator": PRODUCTION | frozenset({"jog", "recover", "teach", "calibrate", "edit_recipes",
                                        "camera", "alarm_ack", "sim_write"}),
    "plc": PRODUCTION,
}
# every valid token may stop the cell
ALWAYS = frozenset({"stop"})

bearer = HTTPBearer(auto_error=False, description="a token from the [api] table of the config")


@dataclass(frozen=True)
class Caller:
    name: str
    role: str

    @property
    def permissions(self) -> frozenset[str]:
        return PERMISSIONS.get(self.role, frozenset()) | ALWAYS

    @property
    def label(self) -> str:
        """How the caller appears in the audit log: ``<door>:<name>(<role>)``, as every door."""
        return f"http:{self.name or self.role}({self.role})"


def token_digest(token: str, salt: str) -> str:
    """What a config stores for a hashed token: hex sha256 of salt + token (UTF-8)."""
    return hashlib.sha256((salt + token).encode()).hexdigest()


@dataclass(frozen=True)
class _Entry:
    caller: Caller
    secret: bytes  # the token itself, or its digest when hashed
    salt: str | None  # None: ``secret`` is the token in the clear


class TokenTable:
    def __init__(self, tokens: list[Any], *, simulated: bool) -> None:
        if not simulated:
            sample = sorted(t.token for t in tokens if getattr(t, "token", None) in SAMPLE_TOKENS)
            if sample:
                raise ConfigError(
                    f"api.tokens: the sample token(s) {', '.join(sample)} are not allowed with "
                    "real hardware; set your own secret tokens in the config")
        self._entries: list[_Entry] = []
        for t in tokens:
            caller = Caller(t.name or t.role, t.role)
            digest = getattr(t, "sha256", None)
            if digest:
                self._entries.append(_Entry(caller, digest.lower().encode(),
                                            getattr(t, "salt", "") or ""))
            else:
                self._entries.append(_Entry(caller, t.token.encode(), None))

    def lookup(self, token: str | None) -> Caller:
        if not token:
            raise AuthError(ErrorCode.unauthorized,
                            "missing bearer token (Authorization: Bearer ...)")
        given = token.encode()
        found: Caller | None = None
        for entry in self._entries:  # no early exit: every entry costs the same
            candidate = given if entry.salt is None else \
                token_digest(token, entry.salt).encode()
            if secrets.compare_digest(candidate, entry.secret) and found is None:
                found = entry.caller
        if found is None:
            raise AuthError(ErrorCode.unauthorized, "unknown token")
        return found


def bearer_of(authorization: str) -> str | None:
    """The token of an ``Authorization: Bearer <token>`` value, None for any other scheme."""
    return authorization[7:].strip() if authorization[:7].lower() == "bearer " else None


def authorise(request: Request, token: str | None, permission: str) -> Caller:
    table: TokenTable = request.app.state.tokens
    caller = table.lookup(token)
    request.state.caller = caller
    if permission not in caller.permissions:
        raise ForbiddenError(ErrorCode.forbidden, f"role {caller.role!r} may not {permission}")
    return caller


def header_token(request: Request, credentials: HTTPAuthorizationCredentials | None
                 ) -> str | None:
    """The token of a route that takes it only in the Authorization header: a ``?token=``
    there is refused, not ignored (it would end up in proxies' and browsers' logs)."""
    if credentials is None and "token" in request.query_params:
        raise AuthError(ErrorCode.unauthorized, "this route takes the token only in the "
                        "Authorization header (?token= is for the GET streaming routes)")
    return credentials.credentials if credentials else None


QUERY_TOKEN = Query(default=None, description="alternative to the header, for <img> and "
                    "EventSource (redacted from the logs)")


def require(permission: str) -> Callable[..., Awaitable[Caller]]:
    """A dependency that authenticates the caller from the Authorization header only and
    checks one permission. ``async``: checked on the event loop in microseconds, never queued
    behind blocking handlers in the worker pool (STOP must not wait for a pool thread)."""

    async def dependency(
        request: Request,
        credentials: HTTPAuthorizationCredentials | None = Depends(bearer),  # noqa: B008
    ) -> Caller:
        return authorise(request, header_token(request, credentials), permission)

    return dependency


def require_stream(permission: str) -> Callable[..., Awaitable[Caller]]:
    """Like ``require`` but also accepts ``?token=``: for GET streaming routes only."""

    async def dependency(
        request: Request,
        credentials: HTTPAuthorizationCredentials | None = Depends(bearer),  # noqa: B008
        token: str | None = QUERY_TOKEN,
    ) -> Caller:
        return authorise(request, credentials.credentials if credentials else token,
                         permission)

    return dependency


# The caller of a route any valid token may use.
Read = Annotated[Caller, Depends(require("read"))]
# The same, for the GET streaming routes that also take ``?token=``.
Stream = Annotated[Caller, Depends(require_stream("read"))]


# STOP without a token: the safe direction, so the cell's own page (and a client on the
# cell's network) can stop without a login when ``[api] anonymous_stop`` is on (the default).
ANONYMOUS_ROLE = "anonymous"  # no entry in PERMISSIONS: it may only stop (ALWAYS)


def anonymous_caller(client_host: str | None) -> Caller:
    """The caller of a STOP without a token, named by its address for the audit log."""
    return Caller(f"anonymous@{client_host}" if client_host else "anonymous", ANONYMOUS_ROLE)


def anonymous_stop_caller(scope: Any) -> Caller | None:
    """The anonymous caller of a request that carries no credential at all (no
    ``Authorization`` header, no ``?token=``) when the app accepts a STOP without one, else
    None: any credential given is checked as usual, and an invalid one stays a 401.

    A browser on another site's page must not stop the cell through an operator's browser
    (a "simple" cross-site POST needs no preflight): such a request carries an ``Origin``
    that is not the cell's own, and is refused."""
    app = scope.get("app")
    if not getattr(getattr(app, "state", None), "anonymous_stop", False):
        return None
    headers = {k.decode("latin-1").lower(): v.decode("latin-1")
               for k, v in scope.get("headers", [])}
    query = parse_qs(scope.get("query_string", b"").decode("latin-1"), keep_blank_values=True)
    if "authorization" in headers or "token" in query:
        return None
    origin = headers.get("origin")
    if origin is not None and _host_of(origin) != headers.get("host", "").lower():
        raise AuthError(ErrorCode.unauthorized,
                        "a STOP without a token is accepted from the cell's own page, not from "
                        f"another site's ({origin})")
    client = scope.get("client")
    return anonymous_caller(client[0] if client else None)


def _host_of(origin: str) -> str:
    """``host[:port]`` of an ``Origin`` value (``null`` and garbage: empty)."""
    scheme, sep, rest = origin.strip().lower().partition("://")
    return rest.split("/")[0] if sep and scheme in ("http", "https") else ""


def require_stop() -> Callable[..., Awaitable[Caller]]:
    """Like ``require("stop")``, but a request with no credential at all is the anonymous
    caller (:func:`anonymous_stop_caller`) when the app accepts a STOP without a token."""

    async def dependency(
        request: Request,
        credentials: HTTPAuthorizationCredentials | None = Depends(bearer),  # noqa: B008
    ) -> Caller:
        caller = anonymous_stop_caller(request.scope)
        if caller is None:
            return authorise(request, header_token(request, credentials), "stop")
        request.state.caller = caller
        return caller

    return dependency
