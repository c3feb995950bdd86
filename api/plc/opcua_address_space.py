"""The OPC UA standard address space (namespace 0), prepared once per installed asyncua.

asyncua builds namespace 0's thousands of nodes from generated code at every server start:
1-2 s on an idle 2-core cell PC, 7 s on a loaded one, the largest part of the service's
start-up. asyncua can instead read them, lazily, from a shelf file it wrote once (its
``Server.init(shelf_file)``), which takes a few tenths of a second.

The shelf is written here, not by the service: ``make install`` (a fresh checkout's and a
cell PC's, docs/deployment.md) runs ``python -m api.plc.opcua_address_space``. asyncua
would write a missing shelf at the start that asked for it, slowly and without a lock, so
two services starting together could read a half-written one; here it is written into a
temporary directory renamed into place in one step, and the server uses it only once it is
complete. A missing shelf only costs the slow start.

The shelf lives beside the interpreter that serves (``sys.prefix``: the project's virtual
environment), named by asyncua's version, so an upgraded asyncua never reads an old one.
``CELL_OPCUA_CACHE`` names another directory.
"""

from __future__ import annotations

import asyncio
import os
import shutil
import sys
import tempfile
import time
from pathlib import Path

import asyncua
from asyncua import Server

SHELF_NAME = "ns0"


def cache_dir() -> Path:
    """The directory holding the shelf of the installed asyncua."""
    root = os.environ.get("CELL_OPCUA_CACHE") or str(Path(sys.prefix) / "var" / "ur-vision-cell")
    return Path(root) / f"opcua-ns0-asyncua-{asyncua.__version__}"


def cached_shelf() -> Path | None:
    """The complete shelf to hand to ``Server.init``, or None (not prepared)."""
    shelf = cache_dir() / SHELF_NAME
    # the marker: an empty file of the shelf's own name, made last (dbm's files beside it)
    return shelf if shelf.is_file() else None


def prepare() -> tuple[Path, float]:
    """Write the shelf unless it is there; returns its path and the seconds it took."""
    t0 = time.perf_counter()
    final = cache_dir()
    shelf = final / SHELF_NAME
    if cached_shelf() is not None:
        return shelf, time.perf_counter() - t0
    final.parent.mkdir(parents=True, exist_ok=True)
    work = Path(tempfile.mkdtemp(prefix=".ns0-", dir=final.parent))
    try:
        asyncio.run(_write(work / SHELF_NAME))
        (work / SHELF_NAME).touch()  # dbm.dumb writes .dat/.dir only; gdbm this very file
        work.chmod(0o755)  # mkdtemp's 0700 would hide it from the service's own user
        try:
            work.rename(final)
        except OSError:  # another install finished first: its shelf is as good
            if cached_shelf() is None:
                raise
    finally:
        shutil.rmtree(work, ignore_errors=True)
    return shelf, time.perf_counter() - t0


async def _write(shelf: Path) -> None:
    server = Server()
    await server.init(shelf)  # no shelf there yet: asyncua builds the nodes, then writes it


if __name__ == "__main__":
    path, took_s = prepare()
    print(f"OPC UA standard address space ready in {took_s:.1f} s ({path})")
