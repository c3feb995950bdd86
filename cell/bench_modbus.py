"""``cell bench modbus``: STOP written by a Modbus PLC, to the moment the arm receives it.

The simulated cell (in-process arm) serves Modbus TCP on a free port; a pymodbus client, as a
PLC, starts a jog-free approach over the handshake and, while the arm moves, writes STOP (one
write of command 4 and a new sequence). Measured per stop: from just before the client's write
to the simulated arm's ``stop`` call (the arm's receipt, timed by a wrapper on the arm driver,
on the same ``time.perf_counter`` clock); and to ``finished == sequence`` in the input
registers as the PLC, polling every 10 ms, sees it. A stop that fails or never reaches the arm
counts as a failure. The host's load changes every figure: report ``uptime`` with them.
"""

from __future__ import annotations

import socket
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

STOP_TARGET_P99_MS = 20.0


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def _pct(values: list[float], q: float) -> float | None:
    return None if not values else float(np.percentile(values, q))


def run(n_stops: int = 100) -> dict[str, Any]:
    from pymodbus.client import ModbusTcpClient

    from api.modbus import Command, Ir, ModbusServer, float_words
    from cell.config import load_config, parse_config
    from cell.runtime import start_cell

    with tempfile.TemporaryDirectory() as tmp:
        data = load_config().model_dump(mode="python")
        data["approach"]["mode"] = "look_and_move"
        data["robot"].update(kind="sim")
        data["sim"]["ur_controller"] = False
        data["gripper"]["kind"] = "none"
        data["api"]["job_db"] = str(Path(tmp) / "jobs.db")
        data["api"]["calibration_dir"] = str(Path(tmp) / "calibration")
        data["opcua"]["enabled"] = False
        data["urscript"]["xmlrpc_port"] = 0
        data["modbus"].update(port=_free_port(), clients=["127.0.0.1"])
        config = parse_config(data)
        cell = start_cell(config)
        received: list[float] = []
        driver = cell.hw.arm
        original = driver.stop

        def timed_stop(*args: Any, **kwargs: Any) -> Any:
            received.append(time.perf_counter())
            return original(*args, **kwargs)

        driver.stop = timed_stop  # type: ignore[method-assign]
        server = ModbusServer(cell, config.modbus)
        server.start()
        client = ModbusTcpClient("127.0.0.1", port=config.modbus.port, timeout=5)
        client.connect()
        to_arm_ms: list[float] = []
        to_registers_ms: list[float] = []
        failures: list[str] = []
        seq = 0
        try:
            for i in range(n_stops):
                seq = seq % 65000 + 1
                client.write_registers(0, [Command.APPROACH, seq, 0, *float_words(
                    150.0 if i % 2 else 60.0)], device_id=1)
                deadline = time.monotonic() + 10.0
                while cell.status().get("state") != "approach" \
                        and time.monotonic() < deadline:
                    time.sleep(0.005)
                time.sleep(0.05)
                seq = seq % 65000 + 1
                n_before = len(received)
                t0 = time.perf_counter()
                r = client.write_registers(0, [Command.STOP, seq], device_id=1)
                if r.isError():
                    failures.append(f"stop {i}: {r}")
                    continue
                deadline = time.monotonic() + 5.0
                while True:
                    regs = client.read_input_registers(0, count=4, device_id=1).registers
                    if regs[Ir.FINISHED_SEQUENCE] == seq:
                        to_registers_ms.append(1000.0 * (time.perf_counter() - t0))
                        break
                    if time.monotonic() > deadline:
                        failures.append(f"stop {i}: not finished in the registers")
                        break
                    time.sleep(0.01)
                if len(received) > n_before:
                    to_arm_ms.append(1000.0 * (received[n_before] - t0))
                else:
                    failures.append(f"stop {i}: the arm never received it")
                deadline = time.monotonic() + 10.0
                while cell.status().get("job") is not None and time.monotonic() < deadline:
                    time.sleep(0.01)
        finally:
            client.close()
            server.close()
            cell.close()
    p99 = _pct(to_arm_ms, 99)
    return {
        "stops": n_stops, "failures": len(failures), "failure_examples": failures[:5],
        "stop_to_arm_ms_max": max(to_arm_ms) if to_arm_ms else None,
        "stop_to_arm_ms_p99": p99, "stop_to_arm_ms_p50": _pct(to_arm_ms, 50),
        "stop_to_registers_ms_p99": _pct(to_registers_ms, 99),
        "stop_to_registers_ms_p50": _pct(to_registers_ms, 50),
        "target_p99_ms": STOP_TARGET_P99_MS,
        "met": p99 is not None and p99 <= STOP_TARGET_P99_MS and not failures,
    }
