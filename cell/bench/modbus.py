"""``cell bench modbus``: STOP written by a Modbus PLC, to the moment the controller has it.

``cell serve`` runs the simulated cell as `make run` does (the real UR adapter and ur_rtde
against the simulated controller, in processes of their own) with Modbus TCP on a free port.
A pymodbus client, standing for the PLC, starts an approach over the handshake and, while the
arm moves, writes STOP (command 4 with a new sequence, one write). Measured per stop, on the
host's monotonic clock that every process shares: from just before the client's write to the
simulated controller's own receipt of the stop command (its RTDE receive time, noted in the
stop log); and to ``finished == sequence`` in the input registers as the PLC, polling every
10 ms, sees it. A stop the controller never receives, or the registers never finish, is a
failure and is counted. The bench is a client like any PLC: it knows the register map from
``docs/plc.md``, not from the server's code. The host's load changes every figure: report
``uptime`` with them.
"""

from __future__ import annotations

import socket
import struct
import tempfile
import time
from pathlib import Path
from typing import Any
from urllib.parse import urlsplit

import numpy as np

from cell.bench.service import serving, to_controller_ms

STOP_TARGET_P99_MS = 20.0
UNIT_ID = 1
# The documented register map (docs/plc.md), as a PLC program declares it.
HR_COMMAND = 0  # then sequence, recipe, standoff_mm (float32, two words)
IR_STATE = 1
IR_FINISHED_SEQUENCE = 3
CMD_APPROACH = 2
CMD_STOP = 4
STATE_BUSY = 1


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def _pct(values: list[float], q: float) -> float | None:
    return None if not values else float(np.percentile(values, q))


def _float_words(value: float) -> list[int]:
    hi, lo = struct.unpack(">HH", struct.pack(">f", value))
    return [hi, lo]


def run(n_stops: int = 100) -> dict[str, Any]:
    from pymodbus.client import ModbusTcpClient

    to_controller: list[float] = []
    to_registers_ms: list[float] = []
    failures: list[str] = []
    port = _free_port()
    with tempfile.TemporaryDirectory(prefix="cell-bench-modbus-") as tmp:
        stop_log = Path(tmp) / "stops.log"
        with serving(stop_log=stop_log, extra_args=["--modbus-port", str(port)]) as (base, _):
            host = urlsplit(base).hostname or "127.0.0.1"  # the service's loopback address
            client = ModbusTcpClient(host, port=port, timeout=5)
            client.connect()
            seq = 0

            def state() -> int:
                return int(client.read_input_registers(
                    0, count=4, device_id=UNIT_ID).registers[IR_STATE])

            try:
                for i in range(n_stops):
                    seq = seq % 65000 + 1
                    client.write_registers(HR_COMMAND, [CMD_APPROACH, seq, 0, *_float_words(
                        150.0 if i % 2 else 60.0)], device_id=UNIT_ID)
                    deadline = time.monotonic() + 10.0
                    while state() != STATE_BUSY and time.monotonic() < deadline:
                        time.sleep(0.005)
                    time.sleep(0.05)  # the arm is under way
                    seq = seq % 65000 + 1
                    t0 = time.monotonic()
                    r = client.write_registers(HR_COMMAND, [CMD_STOP, seq], device_id=UNIT_ID)
                    if r.isError():
                        failures.append(f"stop {i}: {r}")
                        continue
                    ms = to_controller_ms(t0, stop_log)
                    if ms is None:
                        failures.append(f"stop {i}: the controller never received it")
                    else:
                        to_controller.append(ms)
                    deadline = time.monotonic() + 5.0
                    while True:
                        regs = client.read_input_registers(
                            0, count=4, device_id=UNIT_ID).registers
                        if regs[IR_FINISHED_SEQUENCE] == seq:
                            to_registers_ms.append(1000.0 * (time.monotonic() - t0))
                            break
                        if time.monotonic() > deadline:
                            failures.append(f"stop {i}: not finished in the registers")
                            break
                        time.sleep(0.01)
                    deadline = time.monotonic() + 10.0
                    while state() == STATE_BUSY and time.monotonic() < deadline:
                        time.sleep(0.01)
            finally:
                client.close()
    p99 = _pct(to_controller, 99)
    return {
        "stops": n_stops, "stop_to_controller_failed": len(failures),
        "stop_to_controller_ms_p99": None if failures else p99,
        "stop_to_controller_ms_p50": _pct(to_controller, 50),
        "stop_to_controller_ms_max": max(to_controller) if to_controller else None,
        "failure_examples": failures[:5],
        "stop_to_registers_ms_p99": _pct(to_registers_ms, 99),
        "stop_to_registers_ms_p50": _pct(to_registers_ms, 50),
        "target_p99_ms": STOP_TARGET_P99_MS,
        "met": p99 is not None and p99 <= STOP_TARGET_P99_MS and not failures,
    }
