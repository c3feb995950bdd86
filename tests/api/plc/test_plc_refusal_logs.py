"""What the PLC servers log when they refuse a client as configured: one WARNING line in the
server's own words, and nothing from the libraries (pymodbus' DEBUG frames and its ERROR
lines with hex frame dumps; asyncua's ERROR lines about a refused session)."""

from __future__ import annotations

import asyncio
import logging
from pathlib import Path

import pytest
from asyncua import ua

from api.plc.opcua import OpcUaServer
from cell.config.endpoints import opcua_cert_dir
from tests.support.cell import running_cell, sim_config
from tests.support.modbus import modbus_client
from tests.support.net import free_port
from tests.support.opcua import opc_client


def _server_records(caplog: pytest.LogCaptureFixture, prefix: str) -> list[logging.LogRecord]:
    """The records of the service's side (the test's client logs through the same library)."""
    return [r for r in caplog.records if r.name.startswith(prefix)]


def test_a_modbus_read_past_the_map_is_one_warning_and_no_library_output(
        tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    port = free_port()
    config = sim_config(tmp_path, modbus={"port": port, "clients": ["127.0.0.1"]})
    caplog.set_level(logging.DEBUG)
    with running_cell(config) as cell, modbus_client(cell, config.modbus) as client:
        for _ in range(3):  # a PLC polling a wrong address: logged the first time only
            r = client.read_input_registers(25, count=10, device_id=1)
            assert r.isError() and r.exception_code == 2
        assert client.read_input_registers(0, count=1, device_id=5).isError()
        assert not client.read_input_registers(0, count=29, device_id=1).isError()
    assert not _server_records(caplog, "pymodbus")
    assert not [r for r in caplog.records if ">>>>>" in r.getMessage()]
    ours = _server_records(caplog, "api.plc.modbus")
    past = [r for r in ours if "input registers 25-34" in r.getMessage()]
    assert len(past) == 1, [r.getMessage() for r in ours]
    assert past[0].levelno == logging.WARNING
    message = past[0].getMessage()
    assert "refused" in message and "register map" in message and "\n" not in message
    unit = [r for r in ours if "unit 5" in r.getMessage()]
    assert len(unit) == 1 and unit[0].levelno == logging.WARNING
    assert not [r for r in ours if r.levelno >= logging.ERROR]


def test_an_anonymous_opcua_session_refused_by_config_is_one_warning(
        tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    port = free_port()
    url = f"opc.tcp://127.0.0.1:{port}"
    config = sim_config(tmp_path, opcua={"endpoint": url})
    caplog.set_level(logging.DEBUG)

    async def refused(user: str | None, password: str | None) -> None:
        client = opc_client(url, user, password)
        with pytest.raises((ua.UaError, ConnectionError, OSError, TimeoutError)):
            await client.connect()

    with running_cell(config) as cell:
        server = OpcUaServer(cell, config.opcua, opcua_cert_dir(config))
        server.start()
        try:
            caplog.clear()
            asyncio.run(refused(None, None))
            anonymous = list(caplog.records)
            caplog.clear()
            asyncio.run(refused("plc", "wrong"))
            wrong = list(caplog.records)
        finally:
            server.close()
    for records in (anonymous, wrong):
        service = [r for r in records if r.name.startswith(("asyncua.server", "api."))]
        assert not [r for r in service if r.levelno >= logging.ERROR], \
            [(r.name, r.getMessage()) for r in service]
        assert not [r for r in service
                    if r.name.startswith("asyncua") and r.levelno < logging.WARNING]
    said = [r for r in anonymous if r.name == "api.plc.opcua"]
    assert len(said) == 1 and said[0].levelno == logging.WARNING, said
    assert "refused" in said[0].getMessage() and "anonymous" in said[0].getMessage()
    said = [r for r in wrong if r.name == "api.plc.opcua"]
    assert len(said) == 1 and said[0].levelno == logging.WARNING, said
    assert "'plc'" in said[0].getMessage() and "wrong password" in said[0].getMessage()
