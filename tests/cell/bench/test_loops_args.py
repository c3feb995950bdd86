"""`cell bench loops` runs the cell as `make run` serves it unless told otherwise."""

from __future__ import annotations

from pathlib import Path

import pytest

from cell.bench.loops import _config, run_bench_loops
from cell.cli import build_parser


def test_the_loops_bench_drives_the_ur_adapter_by_default() -> None:
    parser = build_parser()
    assert parser.parse_args(["bench", "loops"]).arm == "ur"
    assert parser.parse_args(["bench", "loops", "--arm", "sim"]).arm == "sim"
    with pytest.raises(SystemExit) as exit_:
        parser.parse_args(["bench", "loops", "--arm", "robot"])
    assert exit_.value.code == 2


def test_each_arm_choice_configures_its_own_robot(tmp_path: Path) -> None:
    ur = _config(tmp_path, "ur")
    assert (ur.robot.kind, ur.sim.ur_controller) == ("ur", True)
    assert ur.robot.host.startswith("127.")
    sim = _config(tmp_path, "sim")
    assert (sim.robot.kind, sim.sim.ur_controller) == ("sim", False)


def test_an_unknown_arm_is_refused_before_anything_starts() -> None:
    with pytest.raises(ValueError, match="arm must be one of"):
        run_bench_loops(repeats=1, arm="robot")
