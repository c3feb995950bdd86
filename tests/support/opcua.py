"""An asyncua session on the cell's OPC UA ``Cell`` object, for the PLC-interface tests."""

from __future__ import annotations

import asyncio
import time
from typing import Any

from asyncua import Client

NS = "urn:ur-vision-cell"


def opc_client(url: str, user: str | None, password: str | None = None) -> Client:
    """A client that logs in as ``user`` with the simulated cell's sample password."""
    c = Client(url, timeout=30)
    if user is not None:
        c.set_user(user)
        c.set_password(password or f"sim-{user}")
    return c


class Opc:
    """An asyncua client session on the Cell object (``await Opc(c).open()`` or
    ``async with Opc(c)``)."""

    def __init__(self, client: Client) -> None:
        self.client = client
        self.idx = 0
        self.cell: Any = None

    async def open(self) -> Opc:
        await self.client.connect()
        await self.client.load_data_type_definitions()
        self.idx = await self.client.get_namespace_index(NS)
        self.cell = await self.client.nodes.objects.get_child(f"{self.idx}:Cell")
        return self

    async def close(self) -> None:
        await self.client.disconnect()

    async def __aenter__(self) -> Opc:
        return await self.open()

    async def __aexit__(self, *exc: object) -> None:
        await self.close()

    async def read(self, name: str) -> Any:
        return await (await self.cell.get_child(f"{self.idx}:{name}")).read_value()

    async def call(self, name: str, *args: Any) -> list[Any]:
        out = await self.cell.call_method(f"{self.idx}:{name}", *args)
        return out if isinstance(out, list) else [out]

    async def wait_for(self, name: str, predicate: Any, timeout_s: float) -> Any:
        deadline = time.monotonic() + timeout_s
        while True:
            value = await self.read(name)
            if predicate(value):
                return value
            assert time.monotonic() < deadline, f"{name} = {value!r} after {timeout_s} s"
            await asyncio.sleep(0.05)
