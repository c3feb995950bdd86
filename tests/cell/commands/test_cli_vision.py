"""`cell detect`, `cell estimate` and `cell bench` as a user runs them: JSON and exit codes."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest

from cell.config.schema import load_config
from estimator.transforms import T_from_pose_dict, pose_distance
from fakes.render import random_pose, render_target
from tests.support.paths import REPO


def _cell(*args: str, timeout: float = 120.0) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, "-m", "cell", *args], capture_output=True, text=True,
                          cwd=REPO, timeout=timeout)


@pytest.fixture(scope="module")
def scene(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, np.ndarray]:
    """A rendered view of the built-in simulated cell's target, saved as PNG."""
    config = load_config(None)
    camera, target = config.camera.model(), config.target.model()
    rng = np.random.default_rng(40)
    T = random_pose(rng, camera, target, distance_mm=(350.0, 450.0))
    path = tmp_path_factory.mktemp("cli") / "view.png"
    cv2.imwrite(str(path), render_target(camera, target, T, rng=rng))
    return path, T


def test_detect_json_lists_the_dots(scene: tuple[Path, np.ndarray]) -> None:
    path, T = scene
    out = _cell("detect", str(path), "--json")
    assert out.returncode == 0, out.stderr
    blobs = json.loads(out.stdout)["blobs"]
    assert len(blobs) == 6
    config = load_config(None)
    truth = config.camera.model().project(
        config.target.model().points_mm @ T[:3, :3].T + T[:3, 3])
    found = np.array([[b["u"], b["v"]] for b in blobs])
    assert np.linalg.norm(truth[:, None] - found[None], axis=2).min(axis=1).max() < 0.3
    assert {"u", "v", "area", "circularity", "inertia_ratio", "fill_ratio"} <= set(blobs[0])


def test_estimate_json_is_the_pose_result(scene: tuple[Path, np.ndarray], tmp_path: Path) -> None:
    path, T = scene
    sim = (REPO / "cell" / "configs" / "sim.toml").read_text()
    cfg = tmp_path / "cell.toml"
    cfg.write_text(sim)
    for extra in ([], ["--config", str(cfg)]):
        out = _cell("estimate", str(path), "--json", *extra)
        assert out.returncode == 0, out.stderr + out.stdout
        res = json.loads(out.stdout)
        assert set(res["T_camera_target"]) == {"position_mm", "rotvec_rad"}
        dt, dr = pose_distance(T_from_pose_dict(res["T_camera_target"]), T)
        assert dt < 1.0 and dr < 0.2
        assert res["rms_px"] < 0.5 and isinstance(res["converged"], bool)
        assert sorted(res["matched_ids"]) == list(range(6)) and len(res["blobs"]) == 6
    human = _cell("estimate", str(path))
    assert human.returncode == 0 and "position_mm" in human.stdout


def _error(out: subprocess.CompletedProcess[str]) -> dict[str, str]:
    assert out.returncode == 2, (out.returncode, out.stdout, out.stderr)
    err: dict[str, str] = json.loads(out.stdout)["error"]
    assert err["message"]
    return err


def test_failures_exit_2_with_a_json_error(tmp_path: Path, scene: tuple[Path, np.ndarray]) -> None:
    missing = tmp_path / "nope.png"
    out = _cell("estimate", str(missing), "--json")
    assert _error(out)["code"] == "image_unreadable" and "no such file" in out.stdout
    assert out.stderr == ""  # no OpenCV loader warning next to our error
    junk = tmp_path / "junk.png"
    junk.write_bytes(b"not an image")
    out = _cell("detect", str(junk), "--json")
    assert _error(out)["code"] == "image_unreadable" and out.stderr == ""
    plain = _cell("detect", str(missing))
    assert plain.returncode == 2 and plain.stderr.strip() == (
        f"error (image_unreadable): cannot read {missing}: no such file")

    blank = tmp_path / "blank.png"
    cv2.imwrite(str(blank), np.full((800, 1280), 170, np.uint8))
    err = _error(_cell("estimate", str(blank), "--json"))
    assert err["code"] == "too_few_blobs" and "found 0 blob(s)" in err["message"]

    small = tmp_path / "small.png"
    cv2.imwrite(str(small), np.full((400, 640), 170, np.uint8))
    assert _error(_cell("estimate", str(small), "--json"))["code"] == "image_size_mismatch"

    bad_cfg = tmp_path / "bad.toml"
    bad_cfg.write_text("[camera]\nfx = -1\n")
    err = _error(_cell("estimate", str(scene[0]), "--config", str(bad_cfg), "--json"))
    assert err["code"] == "config_invalid" and "camera" in err["message"]
    err = _error(_cell("detect", str(scene[0]), "--config", str(tmp_path / "x.toml"), "--json"))
    assert err["code"] == "config_invalid"
    plain = _cell("estimate", str(blank))
    assert plain.returncode == 2 and "too_few_blobs" in plain.stderr


def test_bench_json_has_the_documented_keys() -> None:
    out = _cell("bench", "--json", "--frames", "2", "--scenes", "5", "--check")
    r = json.loads(out.stdout)
    # --check: exit 1 exactly when a target is missed (the 100x target is out of reach)
    assert not all(r["targets_met"].values())
    assert out.returncode == 1, out.stderr
    assert out.stderr == ""  # --json: no progress bars, nothing but the document
    for key in ("frame_ms_median", "tracking_ms_median", "speedup_vs_cc", "speedup_vs_sbd",
                "error_ratio_vs_sqpnp_lm"):
        assert isinstance(r[key], float) and np.isfinite(r[key]), key
    assert r["methods"]["pipeline_full"]["failures"] == 0
    assert r["methods"]["pipeline_full"]["translation_err_mm_median"] < 1.0
    assert 0.8 < r["error_ratio_vs_sqpnp_lm"] < 1.5
    assert r["bias_correction"]["frames"] >= 1  # with vs without the perspective-bias step
    bad = _cell("bench", "--json", "--frames", "0")
    assert _error(bad)["code"] == "invalid_argument"
