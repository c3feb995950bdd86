"""The packaging and layering rules every other feature relies on."""

from __future__ import annotations

import ast
import subprocess
import sys
from pathlib import Path

import numpy as np

from estimator.transforms import (
    T_from_pose,
    T_from_ur_pose,
    invert_T,
    pose_distance,
    pose_from_T,
    ur_pose_from_T,
)
from tests.support.paths import REPO

# package -> packages of the project it may import
ALLOWED = {
    "estimator": set(),
    "drivers": {"estimator"},
    "fakes": {"estimator", "drivers"},
    "cell": {"estimator", "drivers", "fakes"},
    "api": {"cell", "estimator"},
}


def _project_imports(path: Path) -> set[str]:
    tree = ast.parse(path.read_text())
    found: set[str] = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            found.update(a.name.split(".")[0] for a in node.names)
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            found.add(node.module.split(".")[0])
    return found & set(ALLOWED)


def test_layering() -> None:
    bad = []
    for pkg, allowed in ALLOWED.items():
        for f in (REPO / pkg).rglob("*.py"):
            extra = _project_imports(f) - allowed - {pkg}
            if extra:
                bad.append(f"{f.relative_to(REPO)} imports {sorted(extra)}")
    assert not bad, "\n".join(bad)


# Business code never asks whether hardware is simulated: only the hardware factory builds fakes
# (and the benchmarks: the estimator's renders its scenes with the fake renderer, the approach,
# service and freeze benchmarks run the simulated cell or controller on a free loopback
# address, the fixed-camera one renders its views with the fixed simulated camera).
MAY_IMPORT_FAKES = {"cell/devices/factory.py", "cell/bench/estimator.py", "cell/bench/approach.py",
                    "cell/bench/service.py", "cell/bench/freeze.py", "cell/bench/fixed.py"}


def test_only_the_factory_builds_fakes() -> None:
    bad = [
        str(f.relative_to(REPO))
        for f in (REPO / "cell").rglob("*.py")
        if "fakes" in _project_imports(f)
        and str(f.relative_to(REPO)) not in MAY_IMPORT_FAKES
    ]
    assert not bad, f"only {sorted(MAY_IMPORT_FAKES)} may import fakes: {bad}"


def test_cli_help() -> None:
    out = subprocess.run([sys.executable, "-m", "cell", "--help"], capture_output=True, text=True)
    assert out.returncode == 0, out.stderr
    assert "COMMAND" in out.stdout


def test_pose_round_trips() -> None:
    rng = np.random.default_rng(1)
    for _ in range(20):
        pos = rng.uniform(-500, 500, 3)
        rv = rng.uniform(-1, 1, 3)
        T = T_from_pose(pos, rv)
        p2, r2 = pose_from_T(T)
        assert np.allclose(T_from_pose(p2, r2), T)
        assert np.allclose(invert_T(T) @ T, np.eye(4))
        ur = ur_pose_from_T(T)
        assert np.allclose(ur[:3], pos / 1000.0)
        assert np.allclose(T_from_ur_pose(ur), T)
        assert pose_distance(T, T) == (0.0, 0.0)
