"""The simulated world's truth is its own: lens and mount apart from the cell's config."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from fastapi.testclient import TestClient

from api.app import create_app
from cell.config.schema import ConfigError
from cell.devices.sim_truth import REALISTIC, resolve
from estimator.transforms import T_from_pose_dict, invert_T, pose_distance
from tests.support.cell import AUTH, running_cell, sim_config

VIEW = AUTH["viewer"]


def test_ideal_world_is_the_config(tmp_path: Path) -> None:
    config = sim_config(tmp_path)
    true = resolve(config)
    believed = config.camera.model()
    assert true.world == "ideal"
    assert (true.camera.fx, true.camera.fy, true.camera.cx, true.camera.cy) == (
        believed.fx, believed.fy, believed.cx, believed.cy)
    np.testing.assert_allclose(true.T_flange_camera, config.hand_eye.T_flange_camera.T())


def test_realistic_world_differs_by_the_documented_offsets(tmp_path: Path) -> None:
    config = sim_config(tmp_path, sim={"world": "realistic"})
    true = resolve(config)
    believed = config.camera.model()
    assert true.camera.fx == pytest.approx(believed.fx * REALISTIC.focal_scale[0])
    assert true.camera.cy == pytest.approx(believed.cy + REALISTIC.principal_offset_px[1])
    assert tuple(true.camera.dist) == pytest.approx(REALISTIC.dist)
    dpos_mm, drot_deg = pose_distance(true.T_flange_camera, config.hand_eye.T_flange_camera.T())
    assert 1.0 < dpos_mm < 3.0 and 0.1 < drot_deg < 1.0


def test_explicit_values_win_over_the_preset(tmp_path: Path) -> None:
    config = sim_config(tmp_path, sim={"world": "realistic",
                                       "camera": {"fx": 900.0, "dist": [0.0, 0.0, 0.0, 0.0]}})
    true = resolve(config)
    assert true.camera.fx == 900.0 and tuple(true.camera.dist) == (0.0, 0.0, 0.0, 0.0)


def test_bad_distortion_is_refused(tmp_path: Path) -> None:
    with pytest.raises(ConfigError):
        sim_config(tmp_path, sim={"camera": {"dist": [0.1, 0.2]}})


def test_sim_truth_reports_lens_and_mount(tmp_path: Path) -> None:
    config = sim_config(tmp_path, sim={"world": "realistic"})
    with running_cell(config) as cell, TestClient(create_app(cell)) as client:
        body = client.get("/api/v1/sim/truth", headers=VIEW).json()
        # what the camera renders with is what the route reports
        assert cell.sim is not None
        true = cell.sim.truth_values()
    assert body["world"] == "realistic"
    assert body["camera"]["fx"] == pytest.approx(true.camera.fx)
    assert body["camera"]["dist"] == pytest.approx(list(REALISTIC.dist))
    T = T_from_pose_dict(body["T_flange_camera"])
    np.testing.assert_allclose(invert_T(T) @ true.T_flange_camera, np.eye(4), atol=1e-9)
