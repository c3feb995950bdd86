"""What the PLC doors (OPC UA, XML-RPC, Modbus) share with HTTP parses their arguments
strictly: a flag or a number where a name is expected, a string or a flag where a number is
expected, is refused with the typed error naming the argument, and nothing moves."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import Any

import pytest

from api import remote
from api.remote import RemoteCaller
from cell.errors import CellError
from cell.features.recipes import parse_spec
from estimator.transforms import pose_distance
from tests.support.cell import running_cell, settled_tcp, sim_config, tcp

PLC = RemoteCaller("opcua", "plc", "plc")
OPERATOR = RemoteCaller("opcua", "op", "operator")


def recipe(config: Any, **target: Any) -> dict[str, Any]:
    t = config.target
    return {"name": "plate-a", "number": 3, "targets": [{
        "points_mm": [list(p) for p in t.points_mm], "dot_diameter_mm": t.dot_diameter_mm,
        **target}]}


def test_plc_arguments_are_not_coerced_and_nothing_moves(tmp_path: Path) -> None:
    config = sim_config(tmp_path)
    with running_cell(config) as cell:
        cell.recipes.save(parse_spec(recipe(config)), "test")
        before = settled_tcp(cell)
        calls: list[tuple[Callable[[], Any], str]] = [
            (lambda: remote.approach(cell, PLC, 40.0, False, ""), "mode"),
            (lambda: remote.approach(cell, PLC, 40.0, "", 0), "taught"),
            (lambda: remote.approach(cell, PLC, "40", ""), "standoff_mm"),
            (lambda: remote.approach(cell, PLC, True, ""), "standoff_mm"),
            (lambda: remote.approach_recipe(cell, PLC, "plate-a", 0), "target"),
            (lambda: remote.approach_recipe(cell, PLC, "plate-a", "", "40"), "standoff_mm"),
            (lambda: remote.track(cell, PLC, 40.0, True), "duration_s"),
            (lambda: remote.gripper(cell, OPERATOR, 1, None), "action"),
        ]
        for call, name in calls:
            with pytest.raises(CellError) as err:
                call()
            assert err.value.code == "invalid_request", (name, err.value.message)
            assert err.value.message.startswith(name), (name, err.value.message)
        assert not cell.commanded()
        assert pose_distance(tcp(cell), before)[0] < 0.01


def test_a_recipe_sent_by_a_plc_is_parsed_strictly_and_checked(tmp_path: Path) -> None:
    config = sim_config(tmp_path)
    with running_cell(config) as cell:
        for target, code, field in (({"speed_mm_s": "150"}, "invalid_recipe", "speed_mm_s"),
                                    ({"standoff_mm": False}, "invalid_recipe", "standoff_mm"),
                                    ({"speed_mm_s": 1e9}, "speed_limit", "speed_mm_s")):
            with pytest.raises(CellError) as err:
                cell.recipes.save(parse_spec(recipe(config, **target)), "test")
            assert err.value.code == code, err.value.message
            assert f"targets.0.{field}" in err.value.message
        assert cell.recipes.list() == []
