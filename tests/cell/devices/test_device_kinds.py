"""Each device table's kinds: every kind has its builder, the one "is real hardware" rule is
the same on the raw file and on the loaded config, and switching a kind is one edit."""

from __future__ import annotations

import itertools
import tomllib
from typing import Any

import pytest

from cell.config.checks import has_real_device
from cell.config.devices import DEVICE_TABLES
from cell.config.schema import ConfigError, parse_config
from cell.devices.factory import BUILDERS
from tests.support.paths import REPO

SIM = tomllib.loads((REPO / "cell" / "configs" / "sim.toml").read_text())


def test_every_kind_has_its_builder() -> None:
    for table in DEVICE_TABLES:
        build = BUILDERS[table.name]
        for kind, cls in table.kinds.items():
            assert build.dispatch(cls) is not build.dispatch(object), (table.name, kind)


def _with(kinds: dict[str, str], ur_controller: bool) -> dict[str, Any]:
    data = {name: dict(values) if isinstance(values, dict) else values
            for name, values in SIM.items()}
    for name, kind in kinds.items():
        data[name]["kind"] = kind
    data["gripper"]["port"] = "/dev/ttyUSB0"
    data["sim"]["ur_controller"] = ur_controller
    data["api"]["state_dir"] = "/var/lib/ur-vision-cell"
    data["api"]["tokens"] = []
    data["opcua"]["enabled"] = False
    data["urscript"]["require_token"] = True
    return data


@pytest.mark.parametrize("ur_controller", [False, True])
def test_the_raw_file_and_the_loaded_config_agree_on_real_hardware(ur_controller: bool) -> None:
    cameras, robots, grippers = (list(t.kinds) for t in DEVICE_TABLES)
    for camera, robot, gripper in itertools.product(cameras, robots, grippers):
        data = _with({"robot": robot, "camera": camera, "gripper": gripper}, ur_controller)
        config = parse_config(data)
        real = (robot == "ur" and not ur_controller) or camera == "oak" or gripper == "robotiq"
        assert config.has_real_device() is real is has_real_device(data), (robot, camera,
                                                                             gripper)


def test_keys_of_another_kind_wait_unused_and_unknown_keys_are_refused() -> None:
    data = _with({"robot": "sim", "gripper": "none"}, ur_controller=False)
    data["camera"]["device_id"] = "18443010D1B2F50F00"  # an OAK's key on the simulated camera
    config = parse_config(data)  # the UR's host, the Robotiq's port: kept in the file, unused
    assert config.robot.kind == "sim" and "host" not in config.robot.model_dump()
    assert config.gripper.model_dump() == {"kind": "none"}
    data["gripper"]["prot"] = "/dev/ttyUSB0"
    with pytest.raises(ConfigError) as err:
        parse_config(data)
    assert [str(p) for p in err.value.problems] == [
        "gripper.prot: unknown key; did you mean 'port'?"]
