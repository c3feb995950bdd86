"""Every start path validates the whole config before touching hardware: the sample or weak
tokens on a real-hardware config are refused while the arm is still unpowered."""

from __future__ import annotations

from pathlib import Path

import pytest

from api.app import app_from_environment
from cell.config.schema import CellConfig, ConfigError
from cell.config.tokens import token_problems
from cell.runtime import start_cell
from fakes.ur_controller.process import ControllerProcess
from tests.support.cell import sim_config


def real_ur_config(tmp_path: Path, host: str, tokens: list[dict[str, str]]) -> CellConfig:
    """A config naming a UR controller at ``host`` as real hardware (no simulated one)."""
    config = sim_config(tmp_path, robot="ur", host=host)
    data = config.model_dump(mode="python")
    data["sim"]["ur_controller"] = False
    data["api"]["tokens"] = tokens
    data["api"]["state_dir"] = str(tmp_path / "state")
    data["opcua"]["enabled"] = False  # checked in tests/api/plc/test_plc_interfaces_config.py
    data["urscript"]["xmlrpc_port"] = 0
    return CellConfig.model_validate(data)


SAMPLE = [{"token": "sim-operator", "role": "operator", "name": "op"}]


def test_sample_tokens_are_refused_before_the_arm_is_powered(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
        capsys: pytest.CaptureFixture[str]) -> None:
    with ControllerProcess() as ctl:
        config = real_ur_config(tmp_path, ctl.host, SAMPLE)
        with pytest.raises(ConfigError, match="sample token"):
            start_cell(config)
        # the application-factory path (uvicorn --factory api.app:app_from_environment)
        toml = tmp_path / "real.toml"
        toml.write_text(_toml(config))
        monkeypatch.setenv("CELL_CONFIG", str(toml))
        with pytest.raises(SystemExit) as exited:
            app_from_environment()
        assert exited.value.code == 2
        assert "sample token" in capsys.readouterr().err
        state = ctl.state()
        assert state["robot_mode"] in ("POWER_OFF", 3), state  # never powered, brakes on


def test_weak_tokens_are_refused_on_real_hardware(tmp_path: Path) -> None:
    weak = {"a": "characters", "a-long-enough-token-but-spaced ": "white space",
            "aaaaaaaaaaaaaaaaaaaaaaaa": "predictable"}
    for token, why in weak.items():
        config = real_ur_config(tmp_path, "127.0.0.1", [
            {"token": token, "role": "operator", "name": "op"}])
        problems = token_problems(config, simulated=False)
        assert problems and why in problems[0], (token, problems)
    good = real_ur_config(tmp_path, "127.0.0.1", [
        {"token": "Zq3vN8r2LxW5mT9cB1yK7dF4", "role": "operator", "name": "op"}])
    assert token_problems(good, simulated=False) == []
    assert token_problems(real_ur_config(tmp_path, "127.0.0.1", SAMPLE), simulated=True) == []


def _toml(config: CellConfig) -> str:
    """The config as TOML (tomllib reads; writing is simple for these plain tables)."""
    lines: list[str] = []
    for table, values in config.model_dump(mode="json", exclude_none=True).items():
        if not isinstance(values, dict):
            continue
        lines.append(f"[{table}]")
        for key, value in values.items():
            lines.append(f"{key} = {_value(value)}")
        lines.append("")
    return "\n".join(lines)


def _value(v: object) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, str):
        return '"' + v.replace("\\", "\\\\").replace('"', '\\"') + '"'
    if isinstance(v, int | float):
        return repr(v)
    if isinstance(v, list | tuple):
        return "[" + ", ".join(_value(x) for x in v) + "]"
    if isinstance(v, dict):
        return "{ " + ", ".join(f"{k} = {_value(x)}" for k, x in v.items()) + " }"
    raise TypeError(type(v))
