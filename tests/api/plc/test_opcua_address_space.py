"""Namespace 0 from its shelf: written once, complete or absent, readable by the service's own
user, and the same nodes a server built from asyncua's code has."""

from __future__ import annotations

import asyncio
import stat
from pathlib import Path

import pytest
from asyncua import Server, ua

from api.plc import opcua_address_space as ns0


async def _server_status_type(shelf: Path | None) -> tuple[str, int, list[str]]:
    server = Server()
    await server.init(shelf)
    node = server.get_node(ua.ObjectIds.Server_ServerStatus)
    name = (await node.read_browse_name()).Name
    children = sorted([(await c.read_browse_name()).Name for c in await node.get_children()])
    type_id = (await node.read_type_definition()).Identifier
    return name, int(type_id), children


def test_the_shelf_is_written_once_and_serves_the_same_nodes(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("CELL_OPCUA_CACHE", str(tmp_path))
    assert ns0.cached_shelf() is None
    shelf, _ = ns0.prepare()
    assert ns0.cached_shelf() == shelf
    assert stat.S_IMODE(shelf.parent.stat().st_mode) == 0o755
    assert [p.name for p in tmp_path.iterdir()] == [shelf.parent.name]  # no work dir left
    assert ns0.prepare()[0] == shelf  # a second install leaves it as it is
    assert asyncio.run(_server_status_type(shelf)) == asyncio.run(_server_status_type(None))
