"""Conventions every `cell` command shares: --version, --json in the same places, exit codes."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

from cell.cli import build_parser, main
from tests.support.paths import REPO

SIM = str(REPO / "cell" / "configs" / "sim.toml")


def test_version(capsys: pytest.CaptureFixture[str]) -> None:
    from importlib import metadata

    with pytest.raises(SystemExit) as exit_:
        main(["--version"])
    assert exit_.value.code == 0
    assert capsys.readouterr().out.strip() == f"cell {metadata.version('ur-vision-cell')}"


def _leaf_commands() -> list[list[str]]:
    """Every command path down to its last action word."""
    import argparse

    def walk(p: argparse.ArgumentParser, path: list[str]) -> list[list[str]]:
        subs = [a for a in p._actions if isinstance(a, argparse._SubParsersAction)]
        if not subs:
            return [path]
        return [leaf for a in subs for name, child in a.choices.items()
                for leaf in walk(child, [*path, name])]

    return walk(build_parser(), [])


def test_every_command_but_serve_takes_json_after_its_last_action_and_after_cell() -> None:
    import argparse

    leaves = _leaf_commands()
    assert ["config", "check"] in leaves and ["teach", "add"] in leaves
    for leaf in leaves:
        parser = build_parser()
        p = parser
        for name in leaf:
            sub = next(a for a in p._actions if isinstance(a, argparse._SubParsersAction))
            p = sub.choices[name]
        options = {o for a in p._actions for o in a.option_strings}
        if leaf == ["serve"]:
            assert "--json" not in options and "--log-format" in options
        else:
            assert "--json" in options, leaf


@pytest.mark.parametrize("argv", [
    ["config", "check", SIM, "--json"],
    ["--json", "config", "check", SIM],
    ["config", "--json", "check", SIM],
])
def test_json_placement_gives_the_same_output(argv: list[str],
                                              capsys: pytest.CaptureFixture[str]) -> None:
    assert main(argv) == 0
    assert json.loads(capsys.readouterr().out)["ok"] is True


def test_teach_json_before_or_after_the_action(capsys: pytest.CaptureFixture[str],
                                               monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.delenv("CELL_TOKEN", raising=False)
    for argv in (["teach", "--json", "list"], ["teach", "list", "--json"]):
        assert main(argv) == 2
        assert json.loads(capsys.readouterr().out)["error"]["code"] == "unauthorized"


def test_without_json_progress_goes_to_stderr_and_json_keeps_it_clean(tmp_path: Path) -> None:
    def run(*args: str) -> subprocess.CompletedProcess[str]:
        return subprocess.run([sys.executable, "-m", "cell", *args], capture_output=True,
                              text=True, cwd=REPO, timeout=120)

    human = run("camera", "snapshot", "--out", str(tmp_path / "a.png"))
    assert human.returncode == 0 and "snapshot: 100%" in human.stderr
    machine = run("camera", "snapshot", "--out", str(tmp_path / "b.png"), "--json")
    assert machine.returncode == 0 and machine.stderr == ""
    json.loads(machine.stdout)
