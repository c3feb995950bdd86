"""Reachability: every pose of a move as the arm's joints will take it, refused
``unreachable`` before anything moves (simulator truth and the guard's commanded moves)."""

from __future__ import annotations

import math
import time
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest

from cell.config.schema import LimitsConfig
from cell.errors import LimitError
from cell.motion.guard import GuardedArm, MotionSlot
from cell.motion.limits import linear_path
from cell.motion.reach import Posture, ReachCheck
from estimator.kinematics import UR_DH, forward
from estimator.transforms import T_from_pose, make_T, pose_distance
from fakes.sim_arm import SimArm
from fakes.ur_sim.engine import MotionEngine
from tests.support.cell import running_cell, settled_tcp, sim_config, tcp

HOME_DEG = np.array([0.0, -90.0, 90.0, -90.0, -90.0, 0.0])
TOOL = T_from_pose([0.0, 0.0, 150.0], [0.0, 0.0, 0.0])
OPEN = dict(workspace_min_mm=(-2000, -2000, -2000), workspace_max_mm=(2000, 2000, 2000),
            tilt_limit_deg=180.0, max_move_mm=3000.0)


def _at(q_deg: np.ndarray) -> Posture:
    q = np.radians(q_deg)
    return Posture(q, forward(UR_DH["ur5e"], q) @ TOOL)


def _pose(q_deg: np.ndarray) -> np.ndarray:
    return _at(q_deg).T_base_tcp


@pytest.fixture
def open_arm() -> Iterator[tuple[GuardedArm, MotionEngine]]:
    """A guarded simulated UR5e with the box and tilt out of the way: reach is the check."""
    engine = MotionEngine(q_rad=[float(v) for v in np.radians(HOME_DEG)])
    try:
        raw = SimArm(engine)
        raw.connect()
        raw.power_on()
        raw.set_tcp(TOOL)
        yield GuardedArm(raw, LimitsConfig(**OPEN), MotionSlot()), engine
    finally:
        engine.close()


def _refused(arm: GuardedArm, T_goal: np.ndarray, match: str) -> LimitError:
    before, n = arm.tcp_pose(), len(arm.commanded())
    with arm.slot.hold("test"), pytest.raises(LimitError) as err:
        arm.move_linear(T_goal, 100.0, 1000.0)
    assert err.value.code == "unreachable" and match in err.value.message, err.value.message
    assert len(arm.commanded()) == n  # nothing was sent
    time.sleep(0.05)
    assert pose_distance(before, arm.tcp_pose())[0] < 1e-6
    return err.value


def test_far_corner_of_the_simulated_box_is_refused_and_nothing_moves(tmp_path: Path) -> None:
    """The sim box's corner 961 mm from the base axis, tool down as at home: in the box, under
    the tilt limit and within one move's distance, out of a UR5e's reach."""
    with running_cell(sim_config(tmp_path)) as cell:
        before = settled_tcp(cell)
        n = len(cell.commanded())
        lo = cell.config.limits.workspace_min_mm
        corner = make_T(before[:3, :3], [lo[0], lo[1], before[2, 3]])
        assert math.hypot(lo[0], lo[1]) > 950.0
        assert cell.arm.guard.in_envelope(corner[:3, 3])
        with cell.core.slot.hold("test"), pytest.raises(LimitError) as err:
            cell.arm.move_linear(corner, 100.0, 500.0, what="corner")
        assert err.value.code == "unreachable"
        assert "out of reach by" in err.value.message, err.value.message
        assert "[-850.0, -450.0" in err.value.message  # the pose that fails is named
        with pytest.raises(LimitError) as jog:  # a jog towards it ends there too
            for _ in range(5):
                cell.jog_step("test", frame="base", translation_mm=[-80.0, -70.0, 0.0],
                              rotation_deg=[0, 0, 0])
        assert jog.value.code == "unreachable"
        moved = [c for c in cell.commanded()[n:] if c.kind != "stop"]
        # the jog's earlier steps moved in reach; none was sent past it
        for c in moved:
            assert math.hypot(*c.T_base_tcp[:2, 3]) < math.hypot(*corner[:2, 3])
        report = cell.arm.check_reachable([("pre-pick", before), ("place", corner)])
        assert report.failed is not None and report.failed.phase == "place"
        assert "place pose" in report.failed.error.message  # type: ignore[union-attr]


def test_refused_corner_leaves_the_true_tcp_and_commands_untouched(tmp_path: Path) -> None:
    with running_cell(sim_config(tmp_path)) as cell:
        before = settled_tcp(cell)
        n = len(cell.commanded())
        lo = cell.config.limits.workspace_min_mm
        corner = make_T(before[:3, :3], [lo[0], lo[1], before[2, 3]])
        with cell.core.slot.hold("test"), pytest.raises(LimitError):
            cell.arm.move_linear(corner, 100.0, 500.0)
        time.sleep(0.2)
        assert len(cell.commanded()) == n
        d_mm, d_deg = pose_distance(before, tcp(cell))
        assert d_mm < 0.01 and d_deg < 0.01


def test_a_reachable_sequence_reports_the_joints_the_arm_will_have(
        open_arm: tuple[GuardedArm, MotionEngine]) -> None:
    arm, _ = open_arm
    T0 = arm.tcp_pose()
    pre = T0 @ T_from_pose([30.0, -20.0, -40.0], [0.0, 0.0, 0.3])
    grasp = pre @ T_from_pose([0.0, 0.0, 40.0], [0.0, 0.0, 0.0])
    report = arm.check_reachable([("pre-pick", pre), ("grasp", grasp), ("retract", pre)])
    assert report.ok and [p.phase for p in report.phases] == ["pre-pick", "grasp", "retract"]
    for p in report.phases:
        assert p.joints_rad is not None
        assert np.allclose(forward(UR_DH["ur5e"], p.joints_rad) @ TOOL, p.T_base_tcp,
                           atol=1e-6)
    # the joints are those the controller takes: move there and compare
    with arm.slot.hold("test"):
        arm.move_linear(pre, 100.0, 1000.0)
    assert np.allclose(arm.joint_positions_rad(), report.phases[0].joints_rad, atol=1e-4)
    assert not arm.check_reachable([("place", T_from_pose([2000, 0, 0], [0, 0, 0]))]).ok


def test_joint_limit_is_refused_naming_the_joint() -> None:
    limits = LimitsConfig(**OPEN, joint_min_deg=(-360.0,) * 5 + (-30.0,),
                          joint_max_deg=(360.0,) * 5 + (30.0,))
    engine = MotionEngine(q_rad=[float(v) for v in np.radians(HOME_DEG)])
    try:
        raw = SimArm(engine)
        raw.connect()
        raw.power_on()
        raw.set_tcp(TOOL)
        arm = GuardedArm(raw, limits, MotionSlot())
        turned = arm.tcp_pose() @ T_from_pose([0, 0, 0], [0.0, 0.0, math.radians(45.0)])
        err = _refused(arm, turned, "wrist 3 joint would reach")
        assert "range -30..30 deg" in err.message
        with arm.slot.hold("test"), pytest.raises(LimitError) as joint:
            arm.move_joint(np.radians(HOME_DEG + np.array([0, 0, 0, 0, 0, 40.0])), 0.5, 1.0)
        assert joint.value.code == "unreachable" and "wrist 3" in joint.value.message
        # within the range it moves
        ok = arm.tcp_pose() @ T_from_pose([0, 0, 0], [0.0, 0.0, math.radians(20.0)])
        with arm.slot.hold("test"):
            arm.move_linear(ok, 100.0, 1000.0)
        assert pose_distance(arm.tcp_pose(), ok)[0] < 0.2
    finally:
        engine.close()


@pytest.mark.parametrize(("start", "goal", "match"), [
    # the wrist: joint 5 from -12 to -2 deg (margin 5)
    ([0, -90, 90, -90, -12, 0], [0, -90, 90, -90, -2, 0], "wrist singularity"),
    # the elbow: joint 3 from 12 to 2 deg, the arm stretching
    ([0, -60, 12, -90, -90, 0], [0, -60, 2, -90, -90, 0], "elbow singularity"),
])
def test_a_move_into_a_singularity_is_refused(start: list[float], goal: list[float],
                                              match: str) -> None:
    engine = MotionEngine(q_rad=[float(v) for v in np.radians(start)])
    try:
        raw = SimArm(engine)
        raw.connect()
        raw.power_on()
        raw.set_tcp(TOOL)
        arm = GuardedArm(raw, LimitsConfig(**OPEN), MotionSlot())
        _refused(arm, _pose(np.array(goal, dtype=float)), match)
    finally:
        engine.close()


def test_shoulder_singularity_and_a_configuration_flip_are_refused() -> None:
    reach = ReachCheck(LimitsConfig(**OPEN), "ur5e")
    home = _at(HOME_DEG)
    # across the base axis: the wrist centre would pass over joint 1's axis
    across = home.T_base_tcp.copy()
    across[:2, 3] = -across[:2, 3]
    with pytest.raises(LimitError) as err:
        reach.check_path(linear_path(home.T_base_tcp, across), "move", home)
    assert err.value.code == "unreachable"
    assert ("shoulder singularity" in err.value.message
            or "too close to the base axis" in err.value.message), err.value.message
    # a pose the arm takes only elbow-down from an elbow-up start
    q_down = HOME_DEG * [1, 1, -1, 1, 1, 1] + [0, -60, 0, 60, 0, 0]
    assert np.sign(np.sin(np.radians(q_down[2]))) < 0
    flipped = _pose(q_down)
    with pytest.raises(LimitError) as err:
        reach.check_path([home.T_base_tcp, flipped], "move", home)
    assert err.value.code == "unreachable"
    # a joint move may flip: the nearest solution is taken
    q = reach.joints_for(flipped, "move", home)
    assert np.allclose(forward(UR_DH["ur5e"], q) @ TOOL, flipped, atol=1e-6)


def test_an_arm_already_inside_a_margin_may_move_out_but_not_deeper() -> None:
    reach = ReachCheck(LimitsConfig(**OPEN), "ur5e")
    at = _at(np.array([0, -90, 90, -90, -3, 0], dtype=float))
    out = _pose(np.array([0, -90, 90, -90, -20, 0], dtype=float))
    deeper = _pose(np.array([0, -90, 90, -90, -1, 0], dtype=float))
    reach.check_path(linear_path(at.T_base_tcp, out), "move", at)
    with pytest.raises(LimitError, match="wrist singularity"):
        reach.check_path(linear_path(at.T_base_tcp, deeper), "move", at)


def test_the_reach_check_costs_little_per_pose() -> None:
    """Measured beside the box and tilt check it runs with (the report quotes both)."""
    reach = ReachCheck(LimitsConfig(**OPEN), "ur5e")
    home = _at(HOME_DEG)
    goal = home.T_base_tcp @ T_from_pose([100.0, 80.0, 120.0], [0.2, -0.1, 0.3])
    path = linear_path(home.T_base_tcp, goal)
    t0 = time.perf_counter()
    for _ in range(20):
        reach.check_path(path, "move", home)
    per_pose_s = (time.perf_counter() - t0) / 20 / len(path)
    assert per_pose_s < 20e-6, per_pose_s
