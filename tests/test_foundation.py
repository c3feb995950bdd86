"""The packaging rules every other feature relies on. The layering itself is checked by the
import contracts in pyproject.toml (``lint-imports``, part of ``make lint``)."""

from __future__ import annotations

import subprocess
import sys

import numpy as np

from estimator.transforms import (
    T_from_pose,
    T_from_ur_pose,
    invert_T,
    pose_distance,
    pose_from_T,
    ur_pose_from_T,
)


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
