"""The simulated world's truth is its own: lens and mount apart from the cell's config."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from fastapi.testclient import TestClient

from api.app import create_app
from cell.config.schema import CellConfig, ConfigError, load_config, parse_config
from cell.devices.factory import build_hardware, simulated_cell_spec
from cell.devices.sim_truth import (
    IDEAL_EFFECTS,
    REALISTIC,
    REALISTIC_EFFECTS,
    effects,
    factory_calibration,
    resolve,
)
from drivers.robotiq import RobotiqGripper
from estimator.transforms import T_from_pose_dict, invert_T, pose_distance
from fakes.fixed_camera import FixedSimCamera
from fakes.ur_sim.kinematics import UR5eKinematics
from tests.support.cell import AUTH, running_cell, sim_config

VIEW = AUTH["viewer"]
FIXED = Path(__file__).parents[3] / "cell" / "configs" / "sim-fixed.toml"


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


def test_realistic_truth_stays_put_when_commissioning_rewrites_the_config(
        tmp_path: Path) -> None:
    # what `cell calibrate ... --write-config` does: new [hand_eye] and [camera] values
    config = sim_config(tmp_path, sim={"world": "realistic"})
    written = sim_config(tmp_path, sim={"world": "realistic"},
                         hand_eye={"T_flange_camera": {"position_mm": [1.1, 59.2, 31.4],
                                                       "rotvec_rad": [0.004, -0.003, 0.006]}},
                         camera={"fx": 806.4, "fy": 805.6, "cx": 643.0, "cy": 397.0})
    before, after = resolve(config), resolve(written)
    assert after.camera == before.camera
    assert factory_calibration(written) == factory_calibration(config)
    np.testing.assert_allclose(after.T_flange_camera, before.T_flange_camera, atol=1e-12)


def test_realistic_fixed_camera_is_off_its_config_too(tmp_path: Path) -> None:
    config = load_config(FIXED)
    data = config.model_dump(mode="python")
    data["sim"]["world"] = "realistic"
    true = resolve(parse_config(data))
    assert config.hand_eye.T_base_camera is not None
    dpos_mm, drot_deg = pose_distance(true.T_flange_camera, config.hand_eye.T_base_camera.T())
    assert 1.0 < dpos_mm < 3.0 and 0.1 < drot_deg < 1.0
    assert true.camera.fx == pytest.approx(config.camera.fx * REALISTIC.focal_scale[0])


def test_sim_truth_reports_lens_and_mount(tmp_path: Path) -> None:
    config = sim_config(tmp_path, sim={"world": "realistic"})
    with running_cell(config) as cell, TestClient(create_app(cell)) as client:
        body = client.get("/api/v1/sim/truth", headers=VIEW).json()
        # the camera reports its nominal lens (its "factory calibration"), renders with the
        # true lens, and the cell computes with the configured intrinsics
        assert client.post("/api/v1/locate", headers=AUTH["plc"]).status_code == 200
        assert cell.hw.camera.latest_frame().camera == factory_calibration(config)
        assert cell.core.locator.camera_model == config.camera.model()
        assert cell.sim is not None
        true = cell.sim.truth_values()
        assert true.camera != factory_calibration(config)
    assert body["world"] == "realistic"
    assert body["camera"]["fx"] == pytest.approx(true.camera.fx)
    assert body["camera"]["dist"] == pytest.approx(list(REALISTIC.dist))
    T = T_from_pose_dict(body["T_flange_camera"])
    np.testing.assert_allclose(invert_T(T) @ true.T_flange_camera, np.eye(4), atol=1e-9)


def _reported_vs_true_tcp_mm(tmp_path: Path, world: str) -> float:
    config = sim_config(tmp_path, sim={"world": world})
    hw = build_hardware(config)
    try:
        hw.arm.connect()
        assert hw.sim is not None
        return float(np.linalg.norm(hw.arm.tcp_pose()[:3, 3] - hw.sim.true_T_base_tcp()[:3, 3]))
    finally:
        hw.close()


def test_realistic_arm_reports_nominal_kinematics_off_the_true_tcp(tmp_path: Path) -> None:
    # the controller reports with the nominal DH table; the true arm is a little off it
    assert 0.1 < _reported_vs_true_tcp_mm(tmp_path, "realistic") < 1.5
    assert _reported_vs_true_tcp_mm(tmp_path / "ideal", "ideal") < 1e-9


def test_true_kinematics_stay_within_a_millimetre_over_the_workspace(tmp_path: Path) -> None:
    def true_kinematics(config: CellConfig) -> UR5eKinematics | None:
        arm = simulated_cell_spec(config).arm
        assert arm is not None
        return arm.true_kinematics()

    kin = true_kinematics(sim_config(tmp_path, sim={"world": "realistic"}))
    assert kin is not None and true_kinematics(sim_config(tmp_path)) is None
    nominal = UR5eKinematics()
    q = np.random.default_rng(0).uniform(-np.pi, np.pi, (500, 6))
    d = [np.linalg.norm(kin.forward(x)[:3, 3] - nominal.forward(x)[:3, 3]) for x in q]
    assert float(np.median(d)) > 0.2 and max(d) < 1.3


def test_effects_presets_and_overrides(tmp_path: Path) -> None:
    ideal = effects(sim_config(tmp_path))
    assert ideal == IDEAL_EFFECTS and ideal.kinematics_exact and not ideal.motion_blur
    real = effects(sim_config(tmp_path, sim={"world": "realistic"}))
    assert real == REALISTIC_EFFECTS and real.camera_latency_s > 0 and real.motion_blur
    mixed = effects(sim_config(tmp_path, sim={"world": "realistic", "camera_latency_s": 0.05,
                                              "motion_blur": False}))
    assert mixed.camera_latency_s == 0.05 and not mixed.motion_blur
    with pytest.raises(ConfigError):
        sim_config(tmp_path, sim={"dh_delta_a_mm": [0.1, 0.2]})


def test_sim_truth_reports_the_effects(tmp_path: Path) -> None:
    config = sim_config(tmp_path, sim={"world": "realistic"})
    with running_cell(config) as cell, TestClient(create_app(cell)) as client:
        body = client.get("/api/v1/sim/truth", headers=VIEW).json()
    fx = body["effects"]
    assert fx["dh_delta_a_mm"] == pytest.approx(list(REALISTIC_EFFECTS.dh_delta_a_mm))
    assert fx["camera_latency_s"] == pytest.approx(REALISTIC_EFFECTS.camera_latency_s)
    assert fx["timestamp_offset_s"] == pytest.approx(REALISTIC_EFFECTS.timestamp_offset_s)
    assert fx["motion_blur"] is True and fx["flicker_depth"] > 0


def test_fixed_camera_takes_the_realistic_camera_effects(tmp_path: Path) -> None:
    # the fixed camera is the same sensor: its frames arrive late, stamped off, smeared, flickered
    data = load_config(Path("cell/configs/sim-fixed.toml")).model_dump(mode="python")
    data["robot"]["kind"], data["sim"]["ur_controller"] = "sim", False
    data["gripper"]["kind"] = "none"
    data["api"]["job_db"] = str(tmp_path / "jobs.db")
    data["sim"]["world"] = "realistic"
    hw = build_hardware(parse_config(data))
    try:
        cam = hw.camera
        assert isinstance(cam, FixedSimCamera)
        fx = REALISTIC_EFFECTS
        assert (cam.latency_s, cam.timestamp_offset_s, cam.motion_blur, cam.flicker_depth) == (
            fx.camera_latency_s, fx.timestamp_offset_s, True, fx.flicker_depth)
    finally:
        hw.close()


@pytest.mark.parametrize(("link", "port_prefix"), [("tcp", "socket://127.0.0.1:"),
                                                   ("pty", "/dev/pts/")])
def test_simulated_gripper_on_a_tool_flange_relay_or_a_pty(tmp_path: Path, link: str,
                                                         port_prefix: str) -> None:
    # the simulated cell reaches its gripper as a UR tool flange's RS-485 relay is reached by
    # default (no tty in the way); a pseudo-terminal stands for a USB-RS-485 adapter
    config = sim_config(tmp_path, gripper="sim")
    data = config.model_dump(mode="python")
    data["gripper"]["link"] = link
    hw = build_hardware(parse_config(data))
    try:
        assert isinstance(hw.gripper, RobotiqGripper)
        assert hw.gripper.port.startswith(port_prefix)
        hw.gripper.connect()
        assert hw.gripper.activate().activated
        assert hw.gripper.close().position_mm == 0.0  # nothing between the fingers at home
    finally:
        hw.close()
