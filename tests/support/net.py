"""Loopback ports for the servers a test starts (HTTP, OPC UA, Modbus, XML-RPC)."""

from __future__ import annotations

import socket


def free_port(host: str = "127.0.0.1") -> int:
    """A TCP port nobody listens on now; the OS may hand it out again later, so start the
    server on it right away."""
    with socket.socket() as s:
        s.bind((host, 0))
        return int(s.getsockname()[1])
