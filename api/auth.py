"""Bearer tokens from config, each with a role; routes ask for a permission, not a role.

Browsers cannot set headers on ``<img>`` and ``EventSource`` requests, so GET routes also accept
the token as ``?token=`` (keep such URLs out of shared logs).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Annotated

from fastapi import Depends, Query, Request
from fastapi.security import HTTPAuthorizationCredentials, HTTPBearer

from api.errors import AuthError, ForbiddenError
from cell.config import SAMPLE_TOKENS, ConfigError, TokenConfig

PERMISSIONS: dict[str, frozenset[str]] = {
    "viewer": frozenset({"read"}),
    "operator": frozenset({"read", "locate", "approach", "track", "jog", "gripper",
                           "sim_write", "recover"}),
    "plc": frozenset({"read", "locate", "approach", "track"}),
}
# every valid token may stop the cell
ALWAYS = frozenset({"stop"})

_bearer = HTTPBearer(auto_error=False, description="a token from the [api] table of the config")


@dataclass(frozen=True)
class Caller:
    name: str
    role: str

    @property
    def permissions(self) -> frozenset[str]:
        return PERMISSIONS.get(self.role, frozenset()) | ALWAYS

    @property
    def label(self) -> str:
        """How the caller appears in the audit log."""
        return f"{self.name or self.role}({self.role})"


class TokenTable:
    def __init__(self, tokens: list[TokenConfig], *, simulated: bool) -> None:
        if not simulated:
            sample = sorted(t.token for t in tokens if t.token in SAMPLE_TOKENS)
            if sample:
                raise ConfigError(
                    f"api.tokens: the sample token(s) {', '.join(sample)} are not allowed with "
                    "real hardware; set your own secret tokens in the config")
        self._by_token = {t.token: Caller(t.name or t.role, t.role) for t in tokens}

    def lookup(self, token: str | None) -> Caller:
        if not token:
            raise AuthError("unauthorized", "missing bearer token (Authorization: Bearer ...)")
        caller = self._by_token.get(token)
        if caller is None:
            raise AuthError("unauthorized", "unknown token")
        return caller


def require(permission: str) -> Callable[..., Caller]:
    """A dependency that authenticates the caller and checks one permission."""

    def dependency(
        request: Request,
        credentials: HTTPAuthorizationCredentials | None = Depends(_bearer),  # noqa: B008
        token: str | None = Query(default=None, description="alternative to the header"),
    ) -> Caller:
        table: TokenTable = request.app.state.tokens
        caller = table.lookup(credentials.credentials if credentials else token)
        if permission not in caller.permissions:
            raise ForbiddenError("forbidden", f"role {caller.role!r} may not {permission}")
        request.state.caller = caller
        return caller

    return dependency


# The caller of a route any valid token may use.
Read = Annotated[Caller, Depends(require("read"))]
