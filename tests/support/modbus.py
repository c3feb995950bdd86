"""A cell's Modbus TCP server with an independent pymodbus client on it, for the PLC tests."""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager

from pymodbus.client import ModbusTcpClient

from api.plc.modbus import ModbusServer
from cell.config.schema import ModbusConfig
from cell.service import Cell


@contextmanager
def modbus_client(cell: Cell, config: ModbusConfig) -> Iterator[ModbusTcpClient]:
    """``cell``'s Modbus server on ``config.port`` and a pymodbus client connected to it from
    127.0.0.1; both closed when the block ends."""
    server = ModbusServer(cell, config)
    server.start()
    client = ModbusTcpClient("127.0.0.1", port=config.port, timeout=5)
    try:
        assert client.connect()
        yield client
    finally:
        client.close()
        server.close()
