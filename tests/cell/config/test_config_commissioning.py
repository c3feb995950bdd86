"""The strict config as a new integrator meets it: every plausible mistake fails to load with
the key and the likely mistake named, loads when the key is explicitly accepted, and `cell
config check` lists every problem at once without hardware."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

from cell.cli import main
from cell.config.schema import ConfigError, load_config, parse_config
from cell.devices.factory import all_simulated
from tests.support.paths import REPO

REAL = (REPO / "cell" / "configs" / "real-cell.example.toml").read_text()
SIM = (REPO / "cell" / "configs" / "sim.toml").read_text()


def _write(tmp_path: Path, text: str, name: str = "cell.toml") -> Path:
    path = tmp_path / name
    path.write_text(text)
    return path


def _edit(text: str, old: str, new: str) -> str:
    assert old in text, old
    return text.replace(old, new, 1)


def _accept(text: str, *keys: str) -> str:
    return _edit(text, "accept = []", "accept = [" + ", ".join(f'"{k}"' for k in keys) + "]")


def _problems(path: Path) -> list[str]:
    with pytest.raises(ConfigError) as err:
        load_config(path)
    assert err.value.code == "config_invalid"
    return [str(p) for p in err.value.problems]


# Plausible mistakes: (old text, mistaken text, key named, words of the likely mistake)
MISTAKES = [
    ('T_flange_tcp = { position_mm = [0.0, 0.0, 150.0]', 'T_flange_tcp = { position_mm = '
     '[0.0, 0.0, 0.15]', "tool.T_flange_tcp.position_mm", "metres"),
    ("speed_mm_s = 100.0", "speed_mm_s = 0.15", "approach.speed_mm_s", "m/s"),
    ("home_joints_deg = [0.0, -90.0, 90.0, -90.0, -90.0, 0.0]",
     "home_joints_deg = [0.0, -1.5708, 1.5708, -1.5708, -1.5708, 0.0]",
     "robot.home_joints_deg", "radians"),
    ("connect_timeout_s = 5.0", "connect_timeout_s = 5000", "robot.connect_timeout_s",
     "milliseconds"),
    ("timeout_s = 0.5", "timeout_s = 500.0", "gripper.timeout_s", "milliseconds"),
]


@pytest.mark.parametrize(("old", "new", "key", "why"), MISTAKES,
                         ids=[m[2] for m in MISTAKES])
def test_each_plausible_mistake_names_key_and_mistake_and_can_be_accepted(
    tmp_path: Path, old: str, new: str, key: str, why: str
) -> None:
    text = _edit(REAL, old, new)
    problems = _problems(_write(tmp_path, text))
    assert len(problems) == 1 and problems[0].startswith(f"{key}: "), problems
    assert why in problems[0] and "[commissioning] accept" in problems[0]
    load_config(_write(tmp_path, _accept(text, key)))  # intended: loads


def test_the_simulated_cell_is_checked_too(tmp_path: Path) -> None:
    text = _edit(SIM, "speed_mm_s = 150.0", "speed_mm_s = 0.15")
    assert _problems(_write(tmp_path, text)) == [
        "approach.speed_mm_s: 0.15 mm/s is under 1 mm/s: is it in m/s? write mm/s (0.15 m/s = "
        "150.0) (if this is intended, list \"approach.speed_mm_s\" in [commissioning] accept)"]


def test_a_quoted_number_is_not_coerced(tmp_path: Path) -> None:
    problems = _problems(_write(tmp_path, _edit(REAL, "width = 1280", 'width = "1280"')))
    assert problems == ["camera.width: Input should be a valid integer (got the string '1280': "
                        "write it without quotes)"]
    problems = _problems(_write(tmp_path, _edit(REAL, "fps = 15.0", 'fps = "15"')))
    assert problems[0].startswith("camera.fps: ") and "without quotes" in problems[0]
    # floats for integers are not truncated either
    problems = _problems(_write(tmp_path, _edit(REAL, "width = 1280", "width = 1280.5")))
    assert problems[0].startswith("camera.width: Input should be a valid integer")


def test_a_lost_robot_table_does_not_run_a_simulated_arm(tmp_path: Path) -> None:
    start = REAL.index("[robot]")
    end = REAL.index("[hand_eye]")
    problems = _problems(_write(tmp_path, REAL[:start] + REAL[end:]))
    assert problems == ['robot: required table: [robot] with kind = "ur" (a UR controller) or '
                        '"sim"']
    problems = _problems(_write(tmp_path, _edit(REAL, 'kind = "ur"\n', "")))
    assert problems == ['robot.kind: required: "ur" (a UR controller at host) or "sim" (the '
                        'simulated arm)']


@pytest.mark.parametrize("table", ["limits", "tool", "hand_eye"])
def test_real_hardware_must_state_limits_tool_and_hand_eye(tmp_path: Path, table: str) -> None:
    start = REAL.index(f"[{table}]")
    end = REAL.index("\n[", start + 1) + 1
    problems = _problems(_write(tmp_path, REAL[:start] + REAL[end:]))
    assert len(problems) == 1 and problems[0].startswith(f"{table}: required with real hardware")
    # the simulated cell may default them
    start = SIM.index(f"[{table}]")
    end = SIM.index("\n[", start + 1) + 1
    assert all_simulated(load_config(_write(tmp_path, SIM[:start] + SIM[end:], "sim.toml")))


def test_limits_without_the_box_use_defaults_only_for_named_keys(tmp_path: Path) -> None:
    """Stating [limits] is what is required; a key left out in it keeps its default."""
    text = _edit(REAL, "max_pose_age_s = 2.0\n", "")
    assert load_config(_write(tmp_path, text)).limits.max_pose_age_s == 2.0


@pytest.mark.parametrize(("old", "new", "key", "hint"), [
    ("speed_mm_s = 100.0", "speed_mms = 100.0", "approach.speed_mms", "speed_mm_s"),
    ("connect_timeout_s = 5.0", "connect_timeout = 5.0", "robot.connect_timeout",
     "connect_timeout_s"),
    ("dot_diameter_mm = 10.0", "dot_diametre_mm = 10.0", "target.dot_diametre_mm",
     "dot_diameter_mm"),
    ("exposure_us = 2000", "exposure_ms = 2", "camera.exposure_ms", "exposure_us"),
    ("slave_id = 9", "slaveid = 9", "gripper.slaveid", "slave_id"),
    ("[limits]", "[limit]", "limit", "limits"),
])
def test_unknown_keys_are_answered_with_the_closest_valid_name(
    tmp_path: Path, old: str, new: str, key: str, hint: str
) -> None:
    text = _edit(REAL, old, new)
    if old == "[limits]":  # the table is then missing too
        text = _accept(text)
    problems = _problems(_write(tmp_path, text))
    assert f"{key}: unknown key; did you mean {hint!r}?" in problems, problems


def test_an_unknown_key_nested_in_a_pose_is_answered(tmp_path: Path) -> None:
    text = _edit(REAL, "T_flange_tcp = { position_mm", "T_flange_tcp = { positon_mm")
    problems = _problems(_write(tmp_path, text))
    assert "tool.T_flange_tcp.positon_mm: unknown key; did you mean 'position_mm'?" in problems


def test_accept_names_only_checked_keys(tmp_path: Path) -> None:
    problems = _problems(_write(tmp_path, _accept(REAL, "tool.T_flange_tcp.position")))
    assert problems == ["commissioning.accept.0: 'tool.T_flange_tcp.position' is not a checked "
                        "key; did you mean 'tool.T_flange_tcp.position_mm'?"]


def test_device_settings_are_validated(tmp_path: Path) -> None:
    cases = [
        ("exposure_us = 2000", "exposure_us = 90000", "camera.exposure_us",
         "does not fit in one frame"),
        ("iso = 400", "iso = 6400", "camera.iso", "less than or equal to 1600"),
        ('socket = "CAM_B"', 'socket = "CAM_Z"', "camera.socket", "CAM_A"),
        ("# focus = 130", "focus = 300", "camera.focus", "0..255"),
        ("# focus = 130", 'focus = "manual"', "camera.focus", "auto"),
        ("baudrate = 115200", "baudrate = 115000", "gripper.baudrate", "115200"),
        ("slave_id = 9", "slave_id = 300", "gripper.slave_id", "247"),
        ("watchdog_s = 0.25", "watchdog_s = 0", "robot.watchdog_s", "greater than 0"),
    ]
    for old, new, key, words in cases:
        problems = _problems(_write(tmp_path, _edit(REAL, old, new)))
        assert any(p.startswith(f"{key}") and words in p for p in problems), (new, problems)
    ok = _edit(_edit(REAL, "# focus = 130", 'focus = "auto"'), 'device_id = ""',
               'device_id = "18443010D1B2F50F00"')
    cfg = load_config(_write(tmp_path, ok))
    assert cfg.camera.focus == "auto" and cfg.camera.device_id == "18443010D1B2F50F00"
    assert (cfg.robot.call_timeout_s, cfg.robot.watchdog_s, cfg.robot.stale_after_s) == \
        (3.0, 0.25, 0.75)
    assert (cfg.gripper.baudrate, cfg.gripper.timeout_s, cfg.gripper.retries) == (115200, 0.5, 1)


def test_robot_and_gripper_settings_reach_the_adapters(tmp_path: Path) -> None:
    """What build_hardware passes: the UR adapter's timing and the Modbus link settings."""
    from cell.config.devices import RobotiqGripperConfig
    from cell.devices.factory import robotiq_gripper
    from drivers.ur.adapter import URArm

    text = _edit(_edit(_edit(REAL, "call_timeout_s = 3.0", "call_timeout_s = 1.5"),
                       "watchdog_s = 0.25", "watchdog_s = 0.4"), "retries = 1", "retries = 3")
    text = _edit(_edit(text, "slave_id = 9", "slave_id = 12"), "baudrate = 115200",
                 "baudrate = 57600")
    cfg = load_config(_write(tmp_path, text))
    assert isinstance(cfg.gripper, RobotiqGripperConfig)
    gripper = robotiq_gripper(cfg.gripper, "/dev/ttyUSB7")
    assert (gripper.port, gripper.slave_id, gripper.baudrate, gripper.timeout_s,
            gripper.retries, gripper.motion_timeout_s, gripper.activation_timeout_s) == \
        ("/dev/ttyUSB7", 12, 57600, 0.5, 3, 5.0, 10.0)
    import cell.devices.factory as factory

    built: dict[str, object] = {}

    class Recorder(URArm):
        def __init__(self, host: str, **kw: float) -> None:
            built.update(host=host, **kw)
            raise RuntimeError("recorded")

    import drivers.ur.adapter

    orig = drivers.ur.adapter.URArm
    drivers.ur.adapter.URArm = Recorder  # type: ignore[misc]
    try:
        with pytest.raises(RuntimeError, match="recorded"):
            factory.build_hardware(cfg)
    finally:
        drivers.ur.adapter.URArm = orig  # type: ignore[misc]
    assert built == {"host": "192.168.1.10", "connect_timeout_s": 5.0, "call_timeout_s": 1.5,
                     "watchdog_s": 0.4, "stale_after_s": 0.75}


def test_state_dir_holds_the_service_state(tmp_path: Path) -> None:
    cfg = load_config(REPO / "cell" / "configs" / "real-cell.example.toml")
    assert cfg.api.state_dir == "/var/lib/ur-vision-cell"
    assert cfg.api.job_db == "/var/lib/ur-vision-cell/jobs.db"
    assert cfg.api.calibration_dir == "/var/lib/ur-vision-cell/calibration"
    assert cfg.api.image_log_dir == "/var/lib/ur-vision-cell/failed-locates"
    from cell.features.teach import TaughtStore

    assert TaughtStore.beside_job_db(cfg.api.job_db).path.parent == Path(cfg.api.state_dir)
    # absent keys default inside it; absolute ones stay; a relative state_dir is refused
    text = REAL.replace('job_db = "jobs.db"\n', "").replace(
        'calibration_dir = "calibration"\n', f'calibration_dir = "{tmp_path}/cal"\n')
    cfg = load_config(_write(tmp_path, text))
    assert cfg.api.job_db == "/var/lib/ur-vision-cell/jobs.db"
    assert cfg.api.calibration_dir == f"{tmp_path}/cal"
    # the resolved config validates to itself (tests and tools re-parse dumped configs)
    assert parse_config(cfg.model_dump(mode="python")) == cfg
    problems = _problems(_write(tmp_path, _edit(REAL, 'state_dir = "/var/lib/ur-vision-cell"',
                                                'state_dir = "var/state"')))
    assert "api.state_dir: state_dir must be an absolute path, got 'var/state'" in problems
    # real hardware without a state dir would write into the working directory
    problems = _problems(_write(tmp_path, _edit(REAL, 'state_dir = "/var/lib/ur-vision-cell"',
                                                'state_dir = ""')))
    assert problems[0].startswith("api.state_dir: empty with real hardware")


def test_config_check_lists_every_problem_and_exits_2(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    text = _edit(_edit(_edit(REAL, "speed_mm_s = 100.0", "speed_mm_s = 0.15"),
                       "width = 1280", 'width = "1280"'), "slave_id = 9", "slaveid = 9")
    path = _write(tmp_path, text)
    assert main(["config", "check", str(path), "--json"]) == 2
    out = json.loads(capsys.readouterr().out)
    assert out["ok"] is False and out["error"]["code"] == "config_invalid"
    keys = [p["key"] for p in out["error"]["problems"]]
    assert sorted(keys) == ["approach.speed_mm_s", "camera.width", "gripper.slaveid"]
    assert main(["config", "check", str(path)]) == 2
    err = capsys.readouterr().err
    assert "3 problem(s)" in err and "approach.speed_mm_s" in err and "'slave_id'" in err
    assert main(["--json", "config", "check", str(tmp_path / "missing.toml")]) == 2
    assert "cannot read" in json.loads(capsys.readouterr().out)["error"]["message"]


def test_config_check_passes_the_shipped_configs_without_hardware(tmp_path: Path) -> None:
    for name, real in (("real-cell.example.toml", True), ("sim.toml", False)):
        path = REPO / "cell" / "configs" / name
        if real:  # as an integrator must: own tokens instead of the samples
            path = _write(tmp_path.parent, _own_tokens(REAL), "real-own-tokens.toml")
        out = subprocess.run([sys.executable, "-m", "cell", "config", "check",
                              str(path), "--json"],
                             capture_output=True, text=True, cwd=tmp_path, timeout=60)
        assert out.returncode == 0, out.stdout + out.stderr
        info = json.loads(out.stdout)
        assert info["ok"] is True and info["real_hardware"] is real
        assert info["warnings"] == []
    # nothing was created in the working directory (no job database, no state)
    assert list(tmp_path.iterdir()) == []


def _own_tokens(text: str) -> str:
    for role in ("viewer", "operator", "plc"):
        text = _edit(text, f'token = "sim-{role}"', f'token = "Zq8-{role}-x7Pn2kVw9LrT4bYc"')
    return text


# Configs each of which ``cell serve`` refuses: (name, how to make it from the example, key)
REFUSED = [
    ("sample tokens on real hardware", lambda t: t, "api.tokens[0] (hmi)"),
    ("simulated camera on a real arm",
     lambda t: _edit(_own_tokens(t), 'kind = "oak"', 'kind = "sim"'), "camera.kind"),
    ("robotiq without a port", lambda t: _edit(_own_tokens(t), 'port = "/dev/ttyUSB0"',
                                               'port = ""'), "gripper.port"),
]


@pytest.mark.parametrize(("make", "key"), [(m, k) for _, m, k in REFUSED],
                         ids=[n for n, _, _ in REFUSED])
def test_every_refusal_of_serve_is_a_check_failure(
        tmp_path: Path, capsys: pytest.CaptureFixture[str], make: object, key: str) -> None:
    from cell.runtime import start_cell

    assert callable(make)
    path = _write(tmp_path, make(REAL))
    assert main(["config", "check", str(path), "--json"]) == 2
    out = json.loads(capsys.readouterr().out)
    assert out["ok"] is False
    assert key in [p["key"] for p in out["error"]["problems"]], out
    # serve refuses before "serving" and before any device is built, with the same problem
    assert main(["serve", "--config", str(path), "--port", "0"]) == 2
    err = capsys.readouterr().err
    assert "serving" not in err and key in err, err
    with pytest.raises(ConfigError) as refused:
        start_cell(load_config(path))
    assert key in [p.key for p in refused.value.problems]


def test_the_factory_refuses_exactly_what_the_check_reports(tmp_path: Path) -> None:
    """Building the hardware (not connecting it) fails iff the shared rules report a problem."""
    from cell.devices.factory import build_hardware, hardware_problems

    text = _edit(_own_tokens(REAL), 'kind = "oak"', 'kind = "sim"')
    for simulated_controller in (False, True):
        data = text if not simulated_controller else text + "\n[sim]\nur_controller = true\n"
        config = load_config(_write(tmp_path, data))
        problems = hardware_problems(config)
        assert bool(problems) is not simulated_controller
        if problems:
            with pytest.raises(ConfigError, match="needs a simulated robot"):
                build_hardware(config)


def test_sim_config_helper_still_builds_a_valid_config(tmp_path: Path) -> None:
    from tests.support.cell import sim_config

    for robot in ("sim", "ur"):
        cfg = sim_config(tmp_path, robot=robot, gripper="sim")
        assert all_simulated(cfg) and cfg.api.job_db == str(tmp_path / "jobs.db")


def test_a_check_reference_needs_three_views(tmp_path: Path) -> None:
    """The reference is recorded by the hand-eye routine, which needs three views: fewer is a
    config error at load, not a recording job that fails later."""
    problems = _problems(_write(tmp_path, SIM + "\n[check]\nviews = 2\n"))
    assert len(problems) == 1 and problems[0].startswith("check.views: "), problems
