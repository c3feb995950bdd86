"""Commissioning CLI as an integrator runs it: the fake gripper process, `cell gripper` over its
pseudo-terminal, and `cell camera snapshot`."""

from __future__ import annotations

import json
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path

import cv2
import pytest

from cell.cli import main
from cell.config.schema import load_config
from tests.support.paths import REPO


def cell(*args: str, timeout: float = 60.0) -> tuple[int, dict[str, object]]:
    out = subprocess.run([sys.executable, "-m", "cell", *args], capture_output=True, text=True,
                         cwd=REPO, timeout=timeout)
    return out.returncode, json.loads(out.stdout)


@pytest.fixture
def fake_gripper_link(tmp_path: Path) -> Iterator[Path]:
    link = tmp_path / "ttyGRIPPER"
    proc = subprocess.Popen(
        [sys.executable, "-m", "fakes.gripper", "--link", str(link), "--object-mm", "42",
         "--activation-s", "0.3"],
        stdout=subprocess.PIPE, text=True, cwd=REPO,
    )
    try:
        assert proc.stdout is not None
        line = proc.stdout.readline()
        assert "ready" in line and str(link) in line
        assert link.is_symlink()
        yield link
    finally:
        proc.terminate()
        proc.wait(timeout=10)
    assert not link.exists()  # the fake cleans up its link


def test_gripper_commissioning_sequence(fake_gripper_link: Path) -> None:
    port = str(fake_gripper_link)
    rc, status = cell("gripper", "--port", port, "status", "--json")
    assert rc == 0 and status["activated"] is False and status["fault"] is None
    assert set(status) >= {"position_mm", "object_detected", "fault"}
    rc, status = cell("gripper", "--port", port, "activate", "--json")
    assert rc == 0 and status["activated"] is True and status["position_mm"] == 85.0
    rc, status = cell("gripper", "--port", port, "close", "--json")
    assert rc == 0 and status["object_detected"] is True
    assert status["position_mm"] == pytest.approx(42.0, abs=0.4)
    rc, status = cell("gripper", "--port", port, "open", "--json")
    assert rc == 0 and status["object_detected"] is False and status["position_mm"] == 85.0


def test_gripper_wrong_slave_id_times_out(fake_gripper_link: Path) -> None:
    rc, out = cell("gripper", "--port", str(fake_gripper_link), "--slave-id", "3",
                   "--timeout", "0.2", "status", "--json")
    assert rc == 2 and out["error"]["code"] == "device_timeout"  # type: ignore[index]
    assert "slave 3" in out["error"]["message"]  # type: ignore[index]


def test_gripper_link_settings_from_the_config(fake_gripper_link: Path, tmp_path: Path) -> None:
    sim_toml = (REPO / "cell" / "configs" / "sim.toml").read_text()
    config = tmp_path / "cell.toml"
    gripper = (f'[gripper]\nkind = "robotiq"\nport = "{fake_gripper_link}"\nslave_id = 3\n'
               'timeout_s = 0.2\n')
    config.write_text(sim_toml.replace('[gripper]\nkind = "sim"\n', gripper).replace(
        "[api]\n", f'[api]\nstate_dir = "{tmp_path}"\n', 1))
    rc, out = cell("gripper", "--config", str(config), "status", "--json")
    assert rc == 2 and "slave 3" in out["error"]["message"]  # type: ignore[index]
    rc, status = cell("gripper", "--config", str(config), "--slave-id", "9", "status", "--json")
    assert rc == 0 and status["activated"] is False
    rc, out = cell("gripper", "status", "--json")
    assert rc == 2 and out["error"]["code"] == "invalid_argument"  # type: ignore[index]


def test_gripper_of_each_kind_from_the_config(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """The simulated cell's gripper (kind = "sim") is driven on its own link; a cell
    without a gripper, or an option its kind does not take, is refused."""
    sim_toml = REPO / "cell" / "configs" / "sim.toml"

    def gripper(*args: str) -> tuple[int, dict[str, object]]:
        rc = main(["gripper", *args, "--json"])
        return rc, json.loads(capsys.readouterr().out)

    rc, status = gripper("--config", str(sim_toml), "activate")
    assert rc == 0 and status["activated"] is True and status["position_mm"] == 85.0
    rc, out = gripper("--config", str(sim_toml), "--port", "/dev/ttyUSB0", "status")
    assert rc == 2 and out["error"]["code"] == "invalid_argument"  # type: ignore[index]
    assert "has no port" in out["error"]["message"]  # type: ignore[index]
    none = tmp_path / "none.toml"
    none.write_text(sim_toml.read_text().replace('[gripper]\nkind = "sim"\n',
                                                 '[gripper]\nkind = "none"\n'))
    rc, out = gripper("--config", str(none), "status")
    assert rc == 2 and out["error"]["code"] == "invalid_argument"  # type: ignore[index]
    assert "no gripper" in out["error"]["message"]  # type: ignore[index]


def test_gripper_missing_port_is_connection_lost(tmp_path: Path) -> None:
    rc, out = cell("gripper", "--port", str(tmp_path / "nothing"), "status", "--json")
    assert rc == 2 and out["error"]["code"] == "connection_lost"  # type: ignore[index]


def test_snapshot_of_the_builtin_sim_camera(tmp_path: Path) -> None:
    out = tmp_path / "frame.png"
    rc, info = cell("camera", "snapshot", "--out", str(out), "--json")
    assert rc == 0 and info["camera"] == "sim"
    image = cv2.imread(str(out), cv2.IMREAD_UNCHANGED)
    cam = load_config(None).camera
    assert image.shape == (cam.height, cam.width) and image.dtype == "uint8"
    dark = (image < 75).astype("uint8")
    n, _, stats, _ = cv2.connectedComponentsWithStats(dark)
    assert sum(1 for i in range(1, n) if stats[i, cv2.CC_STAT_AREA] > 50) == 6  # all dots seen


def test_snapshot_errors_are_json(tmp_path: Path) -> None:
    rc, out = cell("camera", "snapshot", "--out", str(tmp_path / "no" / "dir.png"), "--json")
    assert rc == 2 and out["error"]["code"] == "write_failed"  # type: ignore[index]
    bad = tmp_path / "bad.toml"
    bad.write_text("[camera]\nfx = -1\n")
    rc, out = cell("camera", "snapshot", "--config", str(bad), "--out", str(tmp_path / "f.png"),
                   "--json")
    assert rc == 2 and out["error"]["code"] == "config_invalid"  # type: ignore[index]


def test_snapshot_with_an_oak_config_uses_the_oak_adapter(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    from drivers.oak import camera as oak

    sim_toml = (REPO / "cell" / "configs" / "sim.toml").read_text()
    config = tmp_path / "oak.toml"
    config.write_text(sim_toml.replace(
        "[camera]\n", "[camera]\nkind = \"oak\"\nexposure_us = 1800\niso = 700\n"
        "device_id = \"192.168.1.44\"\nsocket = \"CAM_C\"\n", 1).replace(
        "[api]\n", f"[api]\nstate_dir = \"{tmp_path}\"\n", 1))
    load_config(config)
    opened: list[oak.OakSettings] = []

    def no_device(self: object, settings: oak.OakSettings) -> oak.OakSession:
        opened.append(settings)
        raise RuntimeError("No available devices")

    monkeypatch.setattr(oak.OakDeviceBackend, "open", no_device)
    rc = main(["camera", "snapshot", "--config", str(config), "--out",
               str(tmp_path / "f.png"), "--json"])
    out = json.loads(capsys.readouterr().out)
    assert rc == 2 and out["error"]["code"] == "connection_lost"
    assert "No available devices" in out["error"]["message"]
    assert opened and (opened[0].width, opened[0].height) == (1280, 800)
    assert (opened[0].exposure_us, opened[0].iso) == (1800, 700)
    assert (opened[0].device_id, opened[0].socket) == ("192.168.1.44", "CAM_C")


def test_snapshot_prints_the_settings_in_force(tmp_path: Path) -> None:
    sim_toml = (REPO / "cell" / "configs" / "sim.toml").read_text()
    config = tmp_path / "cell.toml"
    config.write_text(sim_toml.replace("[camera]\n", "[camera]\nexposure_us = 2500\n"
                                       "iso = 800\n", 1))
    rc, info = cell("camera", "snapshot", "--config", str(config), "--out",
                    str(tmp_path / "f.png"), "--json")
    assert rc == 0
    settings = info["settings"]
    assert (settings["exposure_us"], settings["iso"]) == (2500, 800)
    assert settings["device_id"] is None and settings["socket"] is None
    assert settings["focus"] == "auto"  # the simulated camera's motorised lens, on autofocus
    assert settings["fps"] > 0
    out = subprocess.run([sys.executable, "-m", "cell", "camera", "snapshot", "--config",
                          str(config), "--out", str(tmp_path / "g.png")], capture_output=True,
                         text=True, cwd=REPO, timeout=60)
    assert out.returncode == 0
    assert "fps, exposure 2500 us, iso 800, autofocus" in out.stdout
    # a setting the sensor cannot take is an error before any frame
    config.write_text(sim_toml.replace("[camera]\n", "[camera]\nfocus = 300\n", 1))
    rc, info = cell("camera", "snapshot", "--config", str(config), "--out",
                    str(tmp_path / "h.png"), "--json")
    assert rc == 2 and "focus" in info["error"]["message"]  # type: ignore[index]
