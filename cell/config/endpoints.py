"""Where the service's PLC and robot-program interfaces listen, from the config.

``cell serve`` prints these lines and moves the ports (``--opcua-port``, ``--xmlrpc-port``)
before the API package starts the servers (:mod:`api.plc.interfaces`).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any
from urllib.parse import urlparse

from cell.config.schema import CellConfig


def with_ports(config: CellConfig, opcua_port: int | None,
               xmlrpc_port: int | None, modbus_port: int | None = None) -> CellConfig:
    """The config with the OPC UA endpoint's port, the XML-RPC port and the Modbus port
    replaced (``cell serve --opcua-port N --xmlrpc-port N --modbus-port N``); 0 turns that
    interface off."""
    update: dict[str, Any] = {}
    if opcua_port is not None:
        url = urlparse(config.opcua.endpoint)
        endpoint = url._replace(netloc=f"{url.hostname}:{opcua_port}").geturl()
        update["opcua"] = config.opcua.model_copy(update={
            "endpoint": endpoint, "enabled": config.opcua.enabled and opcua_port != 0})
    if xmlrpc_port is not None:
        update["urscript"] = config.urscript.model_copy(update={"xmlrpc_port": xmlrpc_port})
    if modbus_port is not None:
        update["modbus"] = config.modbus.model_copy(update={"port": modbus_port})
    return config.model_copy(update=update)


def opcua_cert_dir(config: CellConfig) -> Path:
    """Where a generated OPC UA certificate is kept: ``opcua/`` beside the job database."""
    return Path(config.api.job_db).resolve().parent / "opcua"


def endpoints(config: CellConfig) -> list[str]:
    """One line per interface the config serves besides HTTP, for ``cell serve``."""
    lines = []
    o = config.opcua
    if o.enabled:
        users = ", ".join(f"{u.name} ({u.role})" for u in o.users)
        lines.append(f"OPC UA on {o.endpoint} (namespace {o.namespace}; security "
                     f"{', '.join(o.security_policies)}; users {users})")
    u = config.urscript
    if u.xmlrpc_port:
        path = "/<token>/RPC2" if u.require_token else "/RPC2"
        lines.append(f"URScript XML-RPC on http://{u.host}:{u.xmlrpc_port}{path}")
    m = config.modbus
    if m.port:
        who = ", ".join(m.clients) if m.clients else "any client"
        lines.append(f"Modbus TCP on {m.host}:{m.port} (unit 1; writes from {who}; STOP from "
                     "any)")
    return lines
