"""The HTTP status of each kind of cell error: the one table every interface answers by
(HTTP itself, and the XML-RPC and OPC UA results that carry an HTTP-like status)."""

from __future__ import annotations

from cell.errors import ErrorKind

STATUS: dict[ErrorKind, int] = {
    "invalid": 422, "conflict": 409, "unavailable": 503, "not_found": 404,
    "unauthorized": 401, "forbidden": 403,
}
