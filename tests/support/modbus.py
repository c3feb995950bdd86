"""A cell's Modbus TCP server with an independent pymodbus client on it, and a PLC's side of
the handshake on such a client, for the PLC tests."""

from __future__ import annotations

import time
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass

import numpy as np
from pymodbus.client import ModbusTcpClient

from api.plc.modbus import N_INPUT, Ir, ModbusServer, float_words, words_float
from cell.config.schema import ModbusConfig
from cell.service import Cell
from estimator.transforms import T_from_pose

TIMEOUT_S = 60.0


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


@dataclass
class Plc:
    """A PLC's side of the handshake, on a pymodbus client."""

    client: ModbusTcpClient
    seq: int = 0

    def inputs(self) -> list[int]:
        r = self.client.read_input_registers(0, count=N_INPUT, device_id=1)
        assert not r.isError(), r
        return list(r.registers)

    def command(self, command: int, recipe: int = 0, standoff_mm: float = 0.0,
                place: int | None = None) -> int:
        """One write of registers 0-4 (command, sequence, recipe, standoff), and 5 (a pick's
        place number) when ``place`` is given: the sequence changes in the same request as
        the command, so the cell never sees half of it."""
        self.seq = (self.seq + 1) & 0xFFFF or 1
        values = [command, self.seq, recipe, *float_words(standoff_mm)]
        if place is not None:
            values.append(place)
        r = self.client.write_registers(0, values, device_id=1)
        assert not r.isError(), r
        return self.seq

    def wait(self, seq: int, poll_s: float = 0.01, timeout_s: float = TIMEOUT_S) -> list[int]:
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            regs = self.inputs()
            if regs[Ir.FINISHED_SEQUENCE] == seq:
                return regs
            time.sleep(poll_s)
        raise AssertionError(f"sequence {seq} did not finish: {self.inputs()}")


def pose_of(regs: list[int]) -> np.ndarray:
    """The pose of input registers 4-15 (mm, rotation vector in rad)."""
    vals = [words_float(regs[Ir.POSE + 2 * i], regs[Ir.POSE + 2 * i + 1]) for i in range(6)]
    return T_from_pose(vals[:3], vals[3:])
