"""The one guarded path: no module but cell/motion/guard.py commands the raw arm.

Checked on the source (every call of an arm's motion method, and every reach for the raw
arm) and on the running objects (what the cell, its locator and the calibration routine hold
is the guarded arm).
"""

from __future__ import annotations

import ast
from pathlib import Path

from cell.motion.guard import GuardedArm
from tests.support.cell import running_cell, sim_config
from tests.support.paths import REPO

MOTION_METHODS = {"move_linear", "move_joint", "jog", "servo_twist", "stop", "servo", "speed",
                  "power_on", "power_off", "recover_protective_stop", "set_tcp", "connect",
                  "disconnect"}
RAW = ("hw.arm", "hardware.arm", ".raw", "_arm", "raw_arm")
# Where the raw arm may be named: built (factory), wrapped once (the cell, the CLI routine),
# connected by the link supervisor (connect, reconnect, power on after a controller restart),
# and the guard itself.
MAY_NAME_RAW = {"cell/motion/guard.py", "cell/devices/factory.py", "cell/service.py",
                "cell/commands/calibrate.py", "cell/supervision/links.py"}
# Modules that may hold the raw arm's type (``drivers.arm.Arm``) to read from it; a module that
# imports it must not call any motion method at all, whatever it names the receiver.
MAY_TYPE_RAW = MAY_NAME_RAW | {"cell/devices/hardware.py", "cell/vision/locate.py"}


def _sources() -> list[tuple[str, ast.Module]]:
    out = []
    for package in ("cell", "api"):
        for path in sorted((REPO / package).rglob("*.py")):
            rel = path.relative_to(REPO).as_posix()
            out.append((rel, ast.parse(path.read_text(), rel)))
    return out


def test_only_the_motion_module_commands_the_raw_arm() -> None:
    offences = []
    for rel, tree in _sources():
        if rel == "cell/motion/guard.py":
            continue
        for node in ast.walk(tree):
            if isinstance(node, ast.Attribute) and node.attr == "arm":
                text = ast.unparse(node)
                if any(text.endswith(r) for r in ("hw.arm", "hardware.arm")) \
                        and rel not in MAY_NAME_RAW:
                    offences.append(f"{rel}:{node.lineno}: names the raw arm ({text})")
            if not (isinstance(node, ast.Call) and isinstance(node.func, ast.Attribute)):
                continue
            if node.func.attr not in MOTION_METHODS:
                continue
            receiver = ast.unparse(node.func.value)
            if any(r in receiver for r in RAW) and not (
                    rel == "cell/supervision/links.py"
                    and node.func.attr in ("power_on", "set_tcp", "connect", "disconnect")):
                offences.append(f"{rel}:{node.lineno}: {receiver}.{node.func.attr}() "
                                "bypasses the guarded arm")
    assert not offences, "\n".join(offences)


def _imports_raw_arm(tree: ast.Module) -> bool:
    return any(isinstance(n, ast.ImportFrom) and n.module == "drivers.arm"
               and any(a.name == "Arm" for a in n.names) for n in ast.walk(tree))


def test_a_module_typed_with_the_raw_arm_commands_nothing() -> None:
    """A receiver renamed from the raw arm (a parameter typed ``Arm``) is caught here: such
    a module may read the arm, never move it."""
    offences = []
    for rel, tree in _sources():
        if not _imports_raw_arm(tree) or rel in MAY_NAME_RAW:
            continue
        if rel not in MAY_TYPE_RAW:
            offences.append(f"{rel}: holds the raw arm's type; take the GuardedArm instead")
        for node in ast.walk(tree):
            if isinstance(node, ast.Call) and isinstance(node.func, ast.Attribute) \
                    and node.func.attr in MOTION_METHODS:
                offences.append(f"{rel}:{node.lineno}: {ast.unparse(node.func)}() in a module "
                                "that holds the raw arm")
    assert not offences, "\n".join(offences)


def test_the_running_cell_holds_only_the_guarded_arm(tmp_path: Path) -> None:
    with running_cell(sim_config(tmp_path)) as cell:
        assert isinstance(cell.arm, GuardedArm)
        assert cell.core.arm is cell.arm
        assert cell.core.locator.arm is cell.arm
        assert cell.core.runner.arm is cell.arm
