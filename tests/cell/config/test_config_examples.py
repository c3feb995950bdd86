"""The shipped configs load, and the real-cell example is recognised as real hardware."""

from __future__ import annotations

from importlib import resources
from pathlib import Path

import pytest

from cell.config.schema import ConfigError, load_config
from cell.devices.factory import all_simulated


def test_builtin_sim_config_is_all_simulated() -> None:
    assert all_simulated(load_config(None))


def test_real_cell_example_validates_and_is_not_simulated() -> None:
    path = resources.files("cell.configs").joinpath("real-cell.example.toml")
    config = load_config(str(path))
    assert not all_simulated(config)
    assert config.robot.kind == "ur" and config.camera.kind == "oak"
    assert config.gripper.kind == "robotiq"


def test_invalid_key_is_named(tmp_path: Path) -> None:
    text = resources.files("cell.configs").joinpath("sim.toml").read_text()
    bad = tmp_path / "bad.toml"
    bad.write_text(text.replace("fx = 800.0", "fx = -1.0"))
    with pytest.raises(ConfigError, match=r"camera\.fx"):
        load_config(bad)
