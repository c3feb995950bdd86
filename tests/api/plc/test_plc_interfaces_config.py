"""``[opcua]`` and ``[urscript]``: defaults off, strict validation naming the key, the sample
passwords and the token-less XML-RPC endpoint refused on real hardware, port moves."""

from __future__ import annotations

from typing import Any

import pytest

from cell.config.endpoints import endpoints, with_ports
from cell.config.schema import ConfigError, load_config, parse_config
from cell.config.tokens import token_problems
from tests.support.paths import REPO


def _sim_with(**tables: dict[str, Any]) -> dict[str, Any]:
    data = load_config().model_dump(mode="python")
    for name, values in tables.items():
        data[name].update(values)
    return data


def test_defaults_are_off_and_sim_serves_both() -> None:
    real = load_config(REPO / "cell" / "configs" / "real-cell.example.toml")
    assert not real.opcua.enabled and real.urscript.xmlrpc_port == 0
    assert endpoints(real) == []
    sim = load_config()
    assert sim.opcua.enabled and sim.opcua.endpoint == "opc.tcp://127.0.0.1:4840"
    assert {(u.name, u.password, u.role) for u in sim.opcua.users} == {
        ("viewer", "sim-viewer", "viewer"), ("operator", "sim-operator", "operator"),
        ("plc", "sim-plc", "plc")}
    assert sim.urscript.xmlrpc_port == 8001
    assert endpoints(sim)[1] == "URScript XML-RPC on http://127.0.0.1:8001/RPC2"


@pytest.mark.parametrize(("table", "values", "key"), [
    ("opcua", {"endpoint": "http://127.0.0.1:4840"}, "opcua.endpoint"),
    ("opcua", {"endpoint": "opc.tcp://127.0.0.1"}, "opcua.endpoint"),
    ("opcua", {"security_policies": ["Basic128Rsa15"]}, "opcua.security_policies"),
    ("opcua", {"security_policies": []}, "opcua.security_policies"),
    ("opcua", {"certificate": "/etc/cert.der"}, "opcua.certificate"),
    ("opcua", {"users": []}, "opcua.users"),
    ("opcua", {"users": [{"name": "a", "password": "x", "role": "admin"}]}, "opcua.users"),
    ("opcua", {"users": [{"name": "a", "password": "x", "role": "plc"}] * 2}, "opcua.users"),
    ("opcua", {"enabeld": True}, "opcua.enabeld"),
    ("urscript", {"xmlrpc_port": 70000}, "urscript.xmlrpc_port"),
    ("urscript", {"xmlrpc_port": "8001"}, "urscript.xmlrpc_port"),
])
def test_invalid_values_name_their_key(table: str, values: dict[str, Any], key: str) -> None:
    with pytest.raises(ConfigError) as err:
        parse_config(_sim_with(**{table: values}))
    assert any(p.key.startswith(key) for p in err.value.problems), err.value.problems


def test_real_hardware_refuses_sample_passwords_and_token_less_xmlrpc() -> None:
    config = parse_config(_sim_with())
    assert token_problems(config, simulated=True) == []
    problems = " ".join(token_problems(config, simulated=False))
    for user in ("viewer", "operator", "plc"):
        assert f"({user}): the password is a sample" in problems
    assert "urscript.require_token" in problems
    fixed = parse_config(_sim_with(
        api={"tokens": [{"token": "Zk3v9Qp2Lm8Xr4Tw7Yb1", "role": "plc"}]},
        opcua={"users": [{"name": "plc", "password": "Zk3v9Qp2Lm8Xr4Tw7Yb1Ab", "role": "plc"}]},
        urscript={"require_token": True}))
    assert token_problems(fixed, simulated=False) == []


def test_ports_move_and_zero_turns_an_interface_off() -> None:
    sim = load_config()
    moved = with_ports(sim, 48400, 18001)
    assert moved.opcua.endpoint == "opc.tcp://127.0.0.1:48400" and moved.opcua.enabled
    assert moved.urscript.xmlrpc_port == 18001
    assert with_ports(sim, None, None, 15020).modbus.port == 15020
    off = with_ports(sim, 0, 0, 0)
    assert not off.opcua.enabled and off.urscript.xmlrpc_port == 0 and off.modbus.port == 0
    assert endpoints(off) == []
    assert with_ports(sim, None, None) == sim
