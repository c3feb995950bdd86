"""``cell calibrate``: JSON output on ViSP's folder and the project's format, errors, config."""

from __future__ import annotations

import json
import shutil
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import pytest

from cell.calibration.dataset import DatasetError, load_dataset, save_project_dataset
from cell.cli import main
from cell.config.schema import load_config
from estimator import CameraModel
from estimator.calib.board import chessboard
from estimator.calib.synthetic import render_board
from estimator.transforms import T_from_pose, T_from_pose_dict, make_T, pose_distance
from tests.support.paths import REPO

VISP_T_FLANGE_CAMERA = T_from_pose(
    np.array([0.05771519632, -0.03392488515, -0.04227690244]) * 1000.0,
    [0.001783530191, 0.009173747947, 1.581782359],
)


def run_json(capsys: pytest.CaptureFixture[str], *argv: str) -> tuple[int, Any]:
    code = main([*argv, "--json"])
    return code, json.loads(capsys.readouterr().out)


def test_hand_eye_json_on_visp_folder(visp_dir: Path, capsys: pytest.CaptureFixture[str]) -> None:
    code, out = run_json(capsys, "calibrate", "hand-eye", str(visp_dir))
    assert code == 1  # the verdict: ViSP's robot poses and images disagree by millimetres
    assert out["dataset"]["format"] == "visp"
    assert set(out["methods"]) == {"tsai", "park", "horaud"}
    for name, m in out["methods"].items():
        assert set(m["T_flange_camera"]) == {"position_mm", "rotvec_rad"}
        d_mm, d_deg = pose_distance(T_from_pose_dict(m["T_flange_camera"]), VISP_T_FLANGE_CAMERA)
        assert d_mm < 1.0 and d_deg < 0.1, name
        assert m["residual"]["mean_mm"] <= 5.41 and m["residual"]["mean_deg"] <= 0.456
        assert len(m["residual"]["per_view_mm"]) == 8
    # the default everywhere, as the routine's: auto, here the hybrid (the poses are off)
    assert out["chosen"] == "hybrid"
    assert out["joint"]["rms_px"] > 2.0 and len(out["joint"]["per_view_rms_px"]) == 8
    assert out["hybrid"]["rms_px"] > 2.0 and len(out["hybrid"]["per_view_rms_px"]) == 8
    assert out["verdict"]["consistent"] is False and "px" in out["verdict"]["text"]
    assert [v["name"] for v in out["views"]] == [f"franka_image-{i}" for i in range(1, 9)]


def test_project_format_gives_the_same_answer(
    visp_dir: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    visp = load_dataset(visp_dir)
    folder = tmp_path / "own"
    folder.mkdir()
    for v in visp.views:
        shutil.copy(v.image_path, folder / v.image_path.name)
    save_project_dataset(folder, visp.camera, visp.board,
                         [(v.image_path.name, v.T_base_flange) for v in visp.views])
    code, out = run_json(capsys, "calibrate", "hand-eye", str(folder), "--method", "park")
    assert code == 1 and out["dataset"]["format"] == "project" and out["chosen"] == "park"
    code, ref = run_json(capsys, "calibrate", "hand-eye", str(visp_dir), "--method", "park")
    got = T_from_pose_dict(out["T_flange_camera"])
    assert pose_distance(got, T_from_pose_dict(ref["T_flange_camera"]))[0] < 1e-6


def test_missing_folder_is_a_json_error(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    code, out = run_json(capsys, "calibrate", "hand-eye", str(tmp_path / "nope"))
    assert code == 2 and out["error"]["code"] == "dataset_not_found"
    code, out = run_json(capsys, "calibrate", "hand-eye", str(tmp_path))  # empty folder
    assert code == 2 and out["error"]["code"] == "dataset_not_found"
    assert "dataset.json" in out["error"]["message"]


def test_unreadable_pose_file_is_a_json_error(
    visp_dir: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    folder = tmp_path / "visp"
    shutil.copytree(visp_dir, folder)
    bad = folder / "franka_pose_rPe_3.yaml"
    bad.chmod(0o644)
    bad.write_text("rows: 6\ncols: 1\ndata:\n  - [0.1]\n  - [oops\n")
    code, out = run_json(capsys, "calibrate", "hand-eye", str(folder))
    assert code == 2
    assert out["error"]["code"] == "pose_unreadable"
    assert "franka_pose_rPe_3.yaml" in out["error"]["message"]


def test_project_format_bad_pose_is_a_json_error(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    data = {
        "format": "ur-vision-cell/hand-eye-dataset", "version": 1,
        "camera": {"fx": 800, "fy": 800, "cx": 640, "cy": 400, "width": 1280, "height": 800},
        "board": {"kind": "chessboard", "cols": 9, "rows": 6, "pitch_mm": 25.0},
        "views": [{"image": "a.png", "T_base_flange": {"position_mm": [1, 2]}}],
    }
    (tmp_path / "dataset.json").write_text(json.dumps(data))
    code, out = run_json(capsys, "calibrate", "hand-eye", str(tmp_path))
    assert code == 2 and out["error"]["code"] == "pose_unreadable"
    (tmp_path / "dataset.json").write_text("{not json")
    code, out = run_json(capsys, "calibrate", "hand-eye", str(tmp_path))
    assert code == 2 and out["error"]["code"] == "dataset_invalid"


def test_write_config_updates_only_hand_eye(
    visp_dir: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    cfg = tmp_path / "cell.toml"
    original = (REPO / "cell" / "configs" / "sim.toml").read_text()
    cfg.write_text(original)
    before = load_config(cfg)
    # ViSP's data disagree with themselves: nothing is written without --force
    code, out = run_json(capsys, "calibrate", "hand-eye", str(visp_dir), "--write-config", str(cfg))
    assert code == 1 and out["written_config"] is None and "--force" in out["not_written"]
    assert cfg.read_text() == original and list(tmp_path.iterdir()) == [cfg]
    code, out = run_json(capsys, "calibrate", "hand-eye", str(visp_dir), "--write-config", str(cfg),
                         "--force")
    assert code == 1 and out["written_config"] == str(cfg)
    after = load_config(cfg)
    written = after.hand_eye.T_flange_camera.T()
    assert pose_distance(written, T_from_pose_dict(out["T_flange_camera"]))[0] < 1e-9
    assert after.model_dump(exclude={"hand_eye"}) == before.model_dump(exclude={"hand_eye"})
    # the old file is kept as a timestamped backup, and the change is reported
    change = out["config_change"]
    backup = Path(change["backup"])
    assert backup.parent == tmp_path and backup.name.startswith("cell.toml.")
    assert backup.name.endswith(".bak") and backup.read_text() == original
    assert change["old_T_flange_camera"]["position_mm"] == [0.0, 60.0, 30.0]
    assert change["distance_mm"] > 10.0
    # every line outside [hand_eye] is kept byte for byte, comments included
    def outside(text: str) -> list[str]:
        lines, inside = [], False
        for line in text.splitlines():
            if line.startswith("["):
                inside = line.strip() == "[hand_eye]"
            if not inside:
                lines.append(line)
        return lines
    assert outside(cfg.read_text()) == outside(original)
    # a second write replaces the table instead of adding another one; the human output
    # prints the change
    assert main(["calibrate", "hand-eye", str(visp_dir), "--method", "park", "--no-refine",
                 "--write-config", str(cfg)]) == 0  # AX = XB alone: the data agree
    human = capsys.readouterr().out
    assert "position_mm" in human and "->" in human and ".bak" in human
    assert cfg.read_text().count("[hand_eye]") == 1
    assert len(list(tmp_path.glob("cell.toml.*.bak"))) == 2  # never over an older backup
    # a broken config is refused and left as it was
    cfg.write_text("[camera\n")
    code, out = run_json(capsys, "calibrate", "hand-eye", str(visp_dir), "--write-config", str(cfg),
                         "--force")
    assert code == 2 and out["error"]["code"] == "config_write_failed"
    assert cfg.read_text() == "[camera\n"


def test_write_config_refuses_what_is_not_a_valid_cell_config(
    visp_dir: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    # a mistyped path does not become a stub config holding only [hand_eye]
    typo = tmp_path / "none.toml"
    code, out = run_json(capsys, "calibrate", "hand-eye", str(visp_dir), "--write-config",
                         str(typo), "--force")
    assert code == 2 and out["error"]["code"] == "config_write_failed"
    assert "does not exist" in out["error"]["message"] and not typo.exists()
    # a TOML fragment, or a config that does not validate, is refused and left as it was
    for text in ("[hand_eye]\n", (REPO / "cell" / "configs" / "sim.toml").read_text()
                 .replace("speed_mm_s = 150.0", "speed_mm_s = 0.15")):
        frag = tmp_path / "frag.toml"
        frag.write_text(text)
        code, out = run_json(capsys, "calibrate", "hand-eye", str(visp_dir), "--write-config",
                             str(frag), "--force")
        assert code == 2 and "not a valid cell config" in out["error"]["message"]
        assert frag.read_text() == text
    assert sorted(p.name for p in tmp_path.iterdir()) == ["frag.toml"]  # no backup either


def test_intrinsics_cli(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    from scipy.spatial.transform import Rotation

    camera = CameraModel(700.0, 700.0, 330.0, 235.0, (), 640, 480)
    board = chessboard(7, 5, 30.0)
    rng = np.random.default_rng(5)
    centre = board.object_points_mm().mean(axis=0)
    for k in range(8):
        R = Rotation.from_rotvec(np.r_[rng.uniform(-0.5, 0.5, 2), rng.uniform(-0.3, 0.3)])
        T = make_T(R.as_matrix(), np.r_[rng.uniform(-30, 30, 2), rng.uniform(550, 750)]
                   - R.as_matrix() @ centre)
        image = render_board(board, camera, T, noise_sigma=1.0, seed=k)
        cv2.imwrite(str(tmp_path / f"img-{k}.png"), image)
    cv2.imwrite(str(tmp_path / "empty.png"), np.full((480, 640), 200, np.uint8))
    code, out = run_json(capsys, "calibrate", "intrinsics", str(tmp_path), "--board", "chessboard",
                         "--cols", "7", "--rows", "5", "--square-mm", "30", "--no-distortion")
    assert code == 0
    for key in ("fx", "fy", "cx", "cy"):
        assert out["camera"][key] == pytest.approx(getattr(camera, key), rel=0.01)
    assert out["rejected"] == ["empty.png"] and len(out["per_image_rms_px"]) == 8
    assert out["rms_px"] < 0.3
    code, out = run_json(capsys, "calibrate", "intrinsics", str(tmp_path / "none"),
                         "--cols", "7", "--rows", "5", "--square-mm", "30")
    assert code == 2 and out["error"]["code"] == "dataset_not_found"
    code, out = run_json(capsys, "calibrate", "intrinsics", str(tmp_path),
                         "--cols", "7", "--rows", "5", "--square-mm", "-1")
    assert code == 2 and out["error"]["code"] == "invalid_argument"


# --- the guided routine on the simulated cell ------------------------------------------------

TRUE_T_FLANGE_CAMERA = {"position_mm": [3.0, 57.5, 34.0], "rotvec_rad": [0.012, -0.02, 0.03]}


def _toml_value(v: Any) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, int | float):
        return repr(v)
    if isinstance(v, str):
        return json.dumps(v)
    if isinstance(v, list | tuple):
        return "[" + ", ".join(_toml_value(x) for x in v) + "]"
    if isinstance(v, dict):
        return "{ " + ", ".join(f"{k} = {_toml_value(x)}" for k, x in v.items()) + " }"
    raise TypeError(v)


def sim_cell_config(path: Path, **sim: Any) -> Path:
    """The built-in simulated cell, in-process arm, camera mount off the [hand_eye] guess."""
    import tomllib

    data = tomllib.loads((REPO / "cell" / "configs" / "sim.toml").read_text())
    tables = {k: data[k] for k in ("camera", "target", "hand_eye", "tool") if k in data}
    tables["robot"] = {**data.get("robot", {}), "kind": "sim"}
    tables["sim"] = {k: v for k, v in data.get("sim", {}).items()
                     if k in ("T_base_target", "noise_std", "blur_sigma_px")}
    tables["sim"].update({"T_flange_camera": TRUE_T_FLANGE_CAMERA, **sim})
    text = "".join(
        f"[{name}]\n" + "".join(f"{k} = {_toml_value(v)}\n" for k, v in t.items()) + "\n"
        for name, t in tables.items()
    )
    path.write_text(text)
    cfg = load_config(path)
    assert cfg.robot.kind == "sim" and cfg.sim.T_flange_camera is not None
    # the routine only aims its views with the [hand_eye] guess, which is millimetres off
    guess = cfg.hand_eye.T_flange_camera.T()
    assert pose_distance(guess, T_from_pose_dict(TRUE_T_FLANGE_CAMERA))[0] > 3.0
    return path


@pytest.mark.slow
def test_routine_recovers_the_simulated_hand_eye(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    cfg = sim_cell_config(tmp_path / "cell.toml")
    saved = tmp_path / "views"
    # 12 views: with 8 the rotation error is ~0.02-0.05 deg, and noise alone
    # reached 0.052 deg once, past the 0.05 deg requirement.
    # the earlier, narrower plan (18 deg tilt, 35 deg roll): half the turning of the default,
    # and the simulated arm here is exact, so it is as accurate
    code, out = run_json(capsys, "calibrate", "routine", "--config", str(cfg), "--views", "12",
                         "--tilt-deg", "18", "--roll-deg", "35",
                         "--speed-mm-s", "250", "--write-config", str(cfg),
                         "--save-dataset", str(saved))
    assert code == 0, out
    truth = T_from_pose_dict(TRUE_T_FLANGE_CAMERA)
    d_mm, d_deg = pose_distance(T_from_pose_dict(out["T_flange_camera"]), truth)
    assert out["chosen"] == "joint"  # auto: the simulated arm here reports exact poses
    assert d_mm < 0.2 and d_deg < 0.05, (d_mm, d_deg)
    assert out["verdict"]["consistent"] is True
    assert out["joint"]["rms_px"] < 0.5 and len(out["views"]) + len(out["failed_views"]) == 12
    written = load_config(cfg).hand_eye.T_flange_camera.T()
    assert pose_distance(written, truth)[0] < 0.2
    # The saved views re-solve offline to the same answer (lossless images, the same
    # observations of the dot target; the poses pass through JSON, and the refinement's
    # tolerance turns that last-digit rounding into micrometres at most).
    assert out["dataset"] == str(saved)
    # ... with the default method, which is the routine's
    assert Path(out["config_change"]["backup"]).is_file()
    code, again = run_json(capsys, "calibrate", "hand-eye", str(saved))
    assert code == 0, again
    assert again["chosen"] == out["chosen"]
    assert again["views"] == out["views"]
    d_mm, d_deg = pose_distance(T_from_pose_dict(again["T_flange_camera"]),
                                T_from_pose_dict(out["T_flange_camera"]))
    assert d_mm < 1e-3 and d_deg < 1e-4


def test_dot_target_dataset_round_trip_and_a_dataset_without_pattern(tmp_path: Path) -> None:
    from estimator import Target

    camera = CameraModel(800.0, 800.0, 639.5, 399.5, (-0.1, 0.02, 0.0, 0.0, 0.0), 1280, 800)
    target = Target(np.array([[0, 0, 0], [60, 0, 0], [60, 40, 0], [0, 40, 0], [20, 15, 0.0]]),
                    8.0, "light")
    poses = [make_T(np.eye(3), [k, 2.0 * k, 500.0]) for k in range(3)]
    images = [np.full((800, 1280), 10 * k, np.uint8) for k in range(3)]
    views = [(f"view-{k:02d}.png", T) for k, T in enumerate(poses)]
    joints = [np.radians([k, -90.0, 90.0, -90.0, -90.0, 3.0 * k]) for k in range(3)]
    dataset = save_project_dataset(tmp_path / "ds", camera, target, views, images, joints,
                                   "ur5e")
    assert dataset.arm_model == "ur5e"
    saved_joints = dataset.joints()
    assert saved_joints is not None and np.allclose(saved_joints, joints, atol=0, rtol=0)
    assert dataset.board is None and dataset.target is not None
    assert np.array_equal(dataset.target.points_mm, target.points_mm)
    assert dataset.target.dot_diameter_mm == 8.0 and dataset.target.polarity == "light"
    assert dataset.camera == camera and [v.name for v in dataset.views] == ["view-00", "view-01",
                                                                            "view-02"]
    for view, T, img in zip(dataset.views, poses, images, strict=True):
        assert pose_distance(view.T_base_flange, T)[0] < 1e-9
        assert np.array_equal(view.load_image(), img)  # PNG: lossless
    data = json.loads((tmp_path / "ds" / "dataset.json").read_text())
    data["views"][1]["joints_rad"] = [0.0, 1.0]
    (tmp_path / "ds" / "dataset.json").write_text(json.dumps(data))
    with pytest.raises(DatasetError, match="joints_rad must be 6 finite angles"):
        load_dataset(tmp_path / "ds")
    del data["target"]
    data["views"][1]["joints_rad"] = joints[1].tolist()
    (tmp_path / "ds" / "dataset.json").write_text(json.dumps(data))
    with pytest.raises(DatasetError) as err:
        load_dataset(tmp_path / "ds")
    assert err.value.code == "dataset_invalid" and '"board" or "target"' in err.value.message


def test_routine_refuses_a_dataset_folder_it_cannot_use_before_moving(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    cfg = sim_cell_config(tmp_path / "cell.toml")
    taken = tmp_path / "taken"
    taken.mkdir()
    (taken / "dataset.json").write_text("{}")
    code, out = run_json(capsys, "calibrate", "routine", "--config", str(cfg),
                         "--save-dataset", str(taken))
    assert code == 2 and out["error"]["code"] == "dataset_exists"
    assert (taken / "dataset.json").read_text() == "{}"  # the old record is untouched
    blocker = tmp_path / "a-file"
    blocker.write_text("")
    code, out = run_json(capsys, "calibrate", "routine", "--config", str(cfg),
                         "--save-dataset", str(blocker / "views"))
    assert code == 2 and out["error"]["code"] == "dataset_unwritable"


def test_routine_without_target_in_view_is_a_json_error(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    far = {"position_mm": [-480.0, 2000.0, 0.0], "rotvec_rad": [3.141592653589793, 0.0, 0.0]}
    cfg = sim_cell_config(tmp_path / "cell.toml", T_base_target=far)
    code, out = run_json(capsys, "calibrate", "routine", "--config", str(cfg))
    assert code == 2 and out["error"]["code"] == "target_not_visible"


def test_routine_refuses_a_speed_above_the_limit_before_anything_moves(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    """The routine drives the arm through the same guard as the service: a speed above
    ``limits.max_speed_mm_s`` is refused before any hardware is even built."""
    import cell.devices.factory

    built: list[object] = []
    monkeypatch.setattr(cell.devices.factory, "build_hardware", lambda cfg: built.append(cfg))
    cfg = sim_cell_config(tmp_path / "cell.toml")
    code, out = run_json(capsys, "calibrate", "routine", "--config", str(cfg),
                         "--speed-mm-s", "300")
    assert code != 0 and out["error"]["code"] == "speed_limit"
    assert "250" in out["error"]["message"]  # the configured limit is named
    assert built == []  # nothing was connected, so nothing could move
