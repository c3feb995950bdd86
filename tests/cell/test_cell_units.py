"""Config, frame chain, safety checks, job/audit store and image log: no hardware needed."""

from __future__ import annotations

import sqlite3
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from cell.config.schema import ConfigError, LimitsConfig, load_config, parse_config
from cell.errors import LimitError, RefusedError, UnavailableError
from cell.jobs.events import EventBus
from cell.jobs.store import JobStore
from cell.motion.limits import SafetyGuard
from cell.results import HomeResult, Pose
from cell.vision.frames import (
    CellFrames,
    approach_tcp,
    mean_pose,
    observation_camera,
    step_goal,
    tilt_deg,
)
from cell.vision.imagelog import ImageLog
from drivers.arm import ArmState
from estimator.transforms import T_from_pose, invert_T, make_T, pose_distance, translation_T

DOWN = T_from_pose([-450.0, -100.0, 300.0], [np.pi, 0.0, 0.0])


def test_builtin_sim_config_has_every_table() -> None:
    c = load_config()
    assert c.robot.kind == "ur" and c.sim.ur_controller
    assert {t.token: t.role for t in c.api.tokens} == {
        "sim-viewer": "viewer", "sim-operator": "operator", "sim-plc": "plc"}
    assert c.approach.tolerance_mm == 0.03 and c.approach.tolerance_deg == 0.02
    assert np.allclose(c.tool.T_flange_tcp.T()[:3, 3], [0, 0, 150])


def test_config_errors_name_the_key() -> None:
    base = load_config().model_dump()
    base["limits"]["max_speed_mm_s"] = -1
    with pytest.raises(ConfigError, match=r"limits\.max_speed_mm_s"):
        parse_config(base)
    base = load_config().model_dump()
    base["robot"]["kind"] = "kuka"
    with pytest.raises(ConfigError, match=r"robot\.kind"):
        parse_config(base)
    base = load_config().model_dump()
    base["api"]["tokens"].append({"token": "sim-plc", "role": "plc"})
    with pytest.raises(ConfigError, match=r"api\.tokens"):
        parse_config(base)
    with pytest.raises(ConfigError, match="workspace_min_mm"):
        parse_config({**load_config().model_dump(),
                      "limits": {"workspace_min_mm": [0, 0, 0], "workspace_max_mm": [0, 1, 1]}})


def test_minimal_config_needs_the_robot_kind(tmp_path: Path) -> None:
    """A file that lost its [robot] table must not quietly run a simulated arm."""
    text = textwrap.dedent("""
        [camera]
        fx = 800.0
        fy = 800.0
        cx = 639.5
        cy = 399.5
        width = 1280
        height = 800
        [target]
        points_mm = [[0,0,0],[60,0,0],[100,10,0],[0,50,0]]
        dot_diameter_mm = 10.0
    """)
    f = tmp_path / "c.toml"
    f.write_text(text)
    with pytest.raises(ConfigError, match=r"robot: required table"):
        load_config(f)
    f.write_text(text + '[robot]\nkind = "sim"\n')
    c = load_config(f)
    assert c.robot.kind == "sim" and c.gripper.kind == "none" and not c.sim.ur_controller


def test_frame_chain_matches_the_issue_formula() -> None:
    rng = np.random.default_rng(3)
    for _ in range(10):
        T_fc = T_from_pose(rng.uniform(-80, 80, 3), rng.uniform(-0.5, 0.5, 3))
        T_ft = T_from_pose(rng.uniform(-200, 200, 3), rng.uniform(-0.5, 0.5, 3))
        T_bt = T_from_pose(rng.uniform(-500, 500, 3), rng.uniform(-2, 2, 3))
        T_ct = T_from_pose(rng.uniform(-100, 100, 3), rng.uniform(-1, 1, 3))
        frames = CellFrames(T_fc, T_ft)
        expected = T_bt @ invert_T(T_ft) @ T_fc @ T_ct
        assert np.allclose(frames.T_base_target(T_bt, T_ct), expected)
        cam = T_from_pose(rng.uniform(-500, 500, 3), rng.uniform(-2, 2, 3))
        assert np.allclose(frames.T_base_camera(frames.tcp_for_camera(cam)), cam)


def test_approach_and_observation_goals() -> None:
    T_bt = T_from_pose([-480, -100, 10], [np.pi, 0, 0])  # plate flat, +z into it (down)
    goal = approach_tcp(T_bt, np.eye(4), 50.0)
    assert np.allclose(goal[:3, 3], [-480, -100, 60])  # 50 mm above, tool z pointing down
    assert np.allclose(goal[:3, 2], [0, 0, -1])
    cam = observation_camera(T_bt, [48, 32, 0], 300.0)
    assert np.allclose(invert_T(T_bt) @ cam[:, 3], [48, 32, -300, 1])
    assert tilt_deg(goal) == pytest.approx(0.0, abs=1e-9)


def test_jog_step_goal_in_base_and_tool_frames() -> None:
    g = step_goal(DOWN, [10, 0, 0], [0, 0, 0], "base")
    assert np.allclose(g[:3, 3] - DOWN[:3, 3], [10, 0, 0])
    g = step_goal(DOWN, [0, 0, 10], [0, 0, 0], "tool")  # tool z points down
    assert np.allclose(g[:3, 3] - DOWN[:3, 3], [0, 0, -10])
    g = step_goal(DOWN, [0, 0, 0], [0, 0, 90], "base")
    assert np.allclose(g[:3, 3], DOWN[:3, 3])
    assert pose_distance(g, DOWN)[1] == pytest.approx(90.0)


def test_mean_pose() -> None:
    T = T_from_pose([1, 2, 3], [0.1, 0.2, 0.3])
    dT = [make_T(Rotation.from_rotvec(v).as_matrix(), d) for v, d in
          (([1e-3, 0, 0], [0.1, 0, 0]), ([-1e-3, 0, 0], [-0.1, 0, 0]))]
    m = mean_pose([T @ dT[0], T @ dT[1]])
    assert pose_distance(m, T)[0] < 1e-9 and pose_distance(m, T)[1] < 1e-6


def _state(**kw: object) -> ArmState:
    base: dict[str, object] = dict(connected=True, robot_mode="RUNNING", safety_status="NORMAL",
                                   moving=False, T_base_tcp=DOWN, joints_rad=np.zeros(6),
                                   timestamp_s=100.0)
    base.update(kw)
    return ArmState(**base)  # type: ignore[arg-type]


def test_safety_guard_refusals() -> None:
    g = SafetyGuard(LimitsConfig(workspace_min_mm=(-800, -400, 20),
                                 workspace_max_mm=(-200, 300, 700), tilt_limit_deg=45,
                                 max_move_mm=300, max_pose_age_s=0.5))
    g.check_arm(_state(), 100.1)
    with pytest.raises(RefusedError) as e:
        g.check_arm(_state(safety_status="PROTECTIVE_STOP"), 100.1)
    assert e.value.code == "protective_stop"
    with pytest.raises(RefusedError) as e:
        g.check_arm(_state(), 101.0)
    assert e.value.code == "stale_pose"
    with pytest.raises(UnavailableError):
        g.check_arm(_state(connected=False), 100.0)
    g.check_goal(DOWN, DOWN @ translation_T(0, 0, 50))
    for goal, code in ((DOWN @ translation_T(0, 0, 290), "outside_envelope"),
                       (make_T(np.eye(3), DOWN[:3, 3]), "tilt_limit"),
                       (translation_T(-450, 250, 300) @ make_T(DOWN[:3, :3], [0, 0, 0]),
                        "move_too_far")):
        with pytest.raises(LimitError) as le:
            g.check_goal(DOWN, goal)
        assert le.value.code == code
    with pytest.raises(LimitError):
        g.check_speed(1e4, 100)
    with pytest.raises(LimitError):
        g.check_jog_speed([200, 0, 0], [0, 0, 0])
    g.check_jog_ahead(DOWN, DOWN @ translation_T(0, 0, 10))
    with pytest.raises(LimitError, match="outside the workspace"):
        g.check_jog_ahead(DOWN, DOWN @ translation_T(0, 0, 290))
    outside = translation_T(0, 0, 500) @ DOWN  # z = 800, above the box
    g.check_jog_ahead(outside, translation_T(0, 0, -10) @ outside)  # back towards the box
    for away in (translation_T(0, 0, 10), translation_T(10, 0, 0)):  # further out, or along
        with pytest.raises(LimitError, match="only moves back towards the box"):
            g.check_jog_ahead(outside, away @ outside)


def test_job_store_records_and_marks_interrupted_jobs(tmp_path: Path) -> None:
    db = tmp_path / "jobs.db"
    store = JobStore(db)
    done = store.create("home", "op", {"speed_deg_s": 30.0})
    home = HomeResult(joints_deg=[0.0, -90.0, 90.0, -90.0, -90.0, 0.0],
                      T_base_tcp=Pose.from_T(np.eye(4)))
    store.finish(done.id, "succeeded", home)
    running = store.create("approach", "plc", {"standoff_mm": 20})
    store.set_progress(running.id, {"cycle": 2})
    store.audit("op", "locate", {"n_frames": 1}, "ok", "rms 0.1")
    assert store.get(done.id).state == "succeeded"  # type: ignore[union-attr]
    assert [j.id for j in store.list_jobs()] == [running.id, done.id]
    journal = sqlite3.connect(db).execute("PRAGMA journal_mode").fetchone()[0]
    assert journal == "wal"
    # A process that dies with a job running: reopen in a fresh process-less store.
    del store
    again = JobStore(db)
    assert again.recovered == [running.id]
    job = again.get(running.id)
    assert job is not None and job.state == "interrupted" and job.error_code == "interrupted"
    finished = again.get(done.id)
    assert finished is not None and finished.state == "succeeded" and finished.result == home
    commands = [e.command for e in again.audit_log()]
    assert commands[:2] == ["recover", "locate"]
    assert JobStore(db).recovered == []


def test_job_store_survives_a_killed_process(tmp_path: Path) -> None:
    db = tmp_path / "jobs.db"
    code = textwrap.dedent(f"""
        import os, signal
        from cell.jobs.store import JobStore
        s = JobStore({str(db)!r})
        s.audit("plc", "approach", {{"standoff_mm": 5}}, "ok")
        j = s.create("approach", "plc", {{"standoff_mm": 5}})
        print(j.id, flush=True)
        os.kill(os.getpid(), signal.SIGKILL)
    """)
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         timeout=60)
    assert out.returncode == -9
    job_id = out.stdout.strip()
    store = JobStore(db)
    assert store.recovered == [job_id]
    assert store.get(job_id).state == "interrupted"  # type: ignore[union-attr]
    assert any(e.command == "approach" and e.caller == "plc" for e in store.audit_log())


def test_image_log_is_a_bounded_ring(tmp_path: Path) -> None:
    log = ImageLog(tmp_path / "img", max_entries=3)
    for i in range(5):
        log.save(np.full((8, 8), i, np.uint8), {"i": i})
    entries = log.entries()
    assert len(entries) == 3
    assert len(list((tmp_path / "img").glob("*.json"))) == 3


def test_event_bus_drops_oldest_for_slow_listeners() -> None:
    bus = EventBus(maxsize=3)
    with bus.subscribe() as sub:
        for i in range(5):
            bus.publish("x", {"i": i})
        got = [sub.get(0.01) for _ in range(4)]
    assert [g["i"] for g in got[:3] if g] == [2, 3, 4] and got[3] is None
    assert bus.n_subscribers == 0


def test_token_table_refuses_sample_tokens_on_real_hardware() -> None:
    from api.auth import TokenTable

    tokens = list(load_config().api.tokens)
    assert TokenTable(tokens, simulated=True).lookup("sim-plc").role == "plc"
    with pytest.raises(ConfigError, match="sample token"):
        TokenTable(tokens, simulated=False)
