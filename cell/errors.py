"""The cell's one error family: every refusal or failure it reports to a caller.

Each error carries a machine-readable :class:`~cell.error_codes.ErrorCode`, an abstract
``kind`` that each interface maps to its own status (HTTP in ``api.http.errors``, OPC UA and
XML-RPC in ``api.remote``, Modbus in ``api.plc.modbus``), and a message that tells a person
what to do. Checks raise before anything is commanded, so a refusal means nothing moved.
Hardware and estimator errors stay in their own layers; the cell maps them into this family
where it meets them.
"""

from __future__ import annotations

from typing import ClassVar, Literal

from cell.error_codes import ErrorCode

ErrorKind = Literal["invalid", "conflict", "unavailable", "not_found", "unauthorized",
                    "forbidden"]


class CellError(Exception):
    """Base of every refusal or failure the cell reports to its callers."""

    kind: ClassVar[ErrorKind] = "conflict"

    def __init__(self, code: ErrorCode, message: str) -> None:
        super().__init__(message)
        self.code = ErrorCode(code)
        self.message = message


class LimitError(CellError):
    """The request itself breaks a configured limit (envelope, speed, tilt, distance)."""

    kind = "invalid"


class RefusedError(CellError):
    """The request is fine but the cell's state forbids it now (busy, stopped, stale pose)."""

    kind = "conflict"


class UnavailableError(CellError):
    """A device or store the request needs is not available (camera lost, arm disconnected)."""

    kind = "unavailable"


class NotFoundError(CellError):
    """No such object: a job, a taught pose, a recipe, an alarm, an image."""

    kind = "not_found"


class AuthError(CellError):
    """A missing or unknown token."""

    kind = "unauthorized"


class ForbiddenError(CellError):
    """The caller's role may not do this."""

    kind = "forbidden"


class Cancelled(RefusedError):
    """The running motion was cancelled by a stop."""
