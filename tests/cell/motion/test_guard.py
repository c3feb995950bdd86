"""The guarded motion path on the in-process simulated cell: each audit finding
reproduced, and what moved (simulator truth, the guard's commanded paths) asserted."""

from __future__ import annotations

import threading
import time
from pathlib import Path

import numpy as np
import pytest

from cell.config.schema import LimitsConfig
from cell.errors import CellError, LimitError, RefusedError
from cell.motion.guard import GuardedArm, MotionSlot
from cell.motion.limits import SafetyGuard, linear_path
from cell.vision.frames import tilt_deg
from drivers.errors import MotionError
from estimator.transforms import T_from_pose, pose_distance, translation_T
from fakes.sim_arm import SimArm
from fakes.ur_sim.engine import MotionEngine
from tests.support.cell import running_cell, settled_tcp, sim_config, tcp, world

HOME_Q = [float(v) for v in np.radians([0.0, -90.0, 90.0, -90.0, -90.0, 0.0])]


def assert_still(cell_tcp: np.ndarray, now: np.ndarray, what: str) -> None:
    d_mm, d_deg = pose_distance(cell_tcp, now)
    assert d_mm < 0.01 and d_deg < 0.01, f"{what}: the arm moved {d_mm:.3f} mm / {d_deg:.3f} deg"


def assert_paths_within(commanded: list, guard: SafetyGuard) -> None:
    """Every commanded move, sampled along its interpolated path, stays in the limits."""
    moves = [c for c in commanded if c.kind in ("move_linear", "move_joint")]
    assert moves
    for c in moves:
        path = list(c.path) if c.path else linear_path(c.T_from, c.T_base_tcp, 0.5, 0.25)
        worst_tilt = max(tilt_deg(T) for T in path)
        assert worst_tilt <= guard.limits.tilt_limit_deg + 1e-6, worst_tilt
        assert all(guard.in_envelope(T[:3, 3]) for T in path)


def test_tilt_is_checked_along_the_path_not_only_at_its_ends(tmp_path: Path) -> None:
    """Two approaches whose goals are within 60 deg but whose moveL between them would sweep
    the tool through 83.6 deg. (The second starts from the first's last locate,
    taken head-on from its observation pose: the oblique view at its goal is the estimator's
    business, not the guard's.)"""
    with running_cell(sim_config(tmp_path, limits={"max_pose_age_s": 30.0})) as cell:
        first = cell.approach("test", standoff_mm=150.0, wait=True,
                              T_target_tcp=T_from_pose([0, 0, 0], [1.0297, 0.0, 0.0]))
        assert first.state == "succeeded", first.error_message
        before = settled_tcp(cell)
        with pytest.raises(LimitError) as err:
            cell.approach("test", speed_mm_s=100.0, wait=True, use_last_locate=True,
                          T_target_tcp=T_from_pose([0, 0, 0], [-1.2486, 0.1479, -2.3451]))
        assert err.value.code == "tilt_limit" and "on its way" in err.value.message
        time.sleep(0.2)
        assert_still(before, tcp(cell), "refused approach")
        assert_paths_within(cell.commanded(), cell.arm.guard)


def test_jogging_outside_the_box_only_reduces_the_violation(tmp_path: Path) -> None:
    """With the TCP above the box top, +z must be refused in every form."""
    with running_cell(sim_config(tmp_path)) as cell:
        z0 = float(tcp(cell)[2, 3])
        box_top = z0 - 38.0  # the audit's 338 mm over a 300 mm top
        limits = cell.config.limits.model_copy(
            update={"workspace_max_mm": (*cell.config.limits.workspace_max_mm[:2], box_top)})
        cell.arm.guard = SafetyGuard(LimitsConfig.model_validate(limits.model_dump()))
        before = tcp(cell)
        for step in ([0, 0, 20.0], [20.0, 0, 0]):  # further out, or along the top
            with pytest.raises(LimitError) as err:
                cell.jog_step("test", frame="base", translation_mm=step, rotation_deg=[0, 0, 0])
            assert err.value.code == "outside_envelope"
        for v in ([0, 0, 50.0], [50.0, 0, 0]):
            with pytest.raises(LimitError):
                cell.jog_start("test", frame="base", linear_mm_s=v, angular_deg_s=[0, 0, 0])
        time.sleep(0.3)
        assert_still(before, tcp(cell), "refused jogs")
        # back towards the box: allowed, and z only goes down
        cell.jog_start("test", frame="base", linear_mm_s=[0, 0, -50.0], angular_deg_s=[0, 0, 0])
        t_end = time.monotonic() + 0.5
        while time.monotonic() < t_end:
            cell.heartbeat("test")
            time.sleep(0.05)
        cell.stop("test")
        after = settled_tcp(cell)
        assert after[2, 3] < z0 - 5.0
        assert all(c.velocity is None or c.velocity[2] <= 0 for c in cell.commanded())
        # a step that ends still outside but closer is allowed too (reduces the violation)
        cell.jog_step("test", frame="base", translation_mm=[0, 0, -5.0], rotation_deg=[0, 0, 0])


@pytest.mark.parametrize("speed", [0.005, 5e-324, 1e-300])
def test_speeds_that_round_to_nothing_are_refused_with_a_limit_code(
        tmp_path: Path, speed: float) -> None:
    """Refused before anything moves: a creeping step would fail after 0.07 s while the arm
    kept moving."""
    with running_cell(sim_config(tmp_path)) as cell:
        before = tcp(cell)
        with pytest.raises(LimitError) as err:
            cell.jog_step("test", frame="tool", translation_mm=[0, 0, 5.0],
                          rotation_deg=[0, 0, 0], speed_mm_s=speed)
        assert err.value.code == "jog_speed_limit"
        with pytest.raises(LimitError) as err:
            cell.approach("test", speed_mm_s=speed)
        assert err.value.code == "speed_limit"
        time.sleep(0.2)
        assert_still(before, tcp(cell), "refused slow moves")
        assert cell.core.slot.current is None


class _FailsAfterSending(SimArm):
    """A controller that takes the move and then reports it failed while the arm goes on
    moving (what a misread motion end looks like)."""

    def move_linear(self, T_base_tcp: np.ndarray, speed_mm_s: float, accel_mm_s2: float,
                    wait: bool = True) -> None:
        super().move_linear(T_base_tcp, speed_mm_s, accel_mm_s2, wait=False)
        time.sleep(0.1)
        raise MotionError("simulated: the controller reported the move failed")


def test_a_failed_move_ends_with_the_arm_stopped_and_still_before_the_slot_is_free() -> None:
    engine = MotionEngine(q_rad=HOME_Q)
    try:
        raw = _FailsAfterSending(engine)
        raw.connect()
        raw.power_on()
        arm = GuardedArm(raw, LimitsConfig(workspace_min_mm=(-900, -900, 0),
                                           workspace_max_mm=(900, 900, 1000)), MotionSlot())
        T0 = arm.tcp_pose()
        with arm.slot.hold("test"), pytest.raises(RefusedError) as err:
            arm.move_linear(translation_T(0, 0, -150.0) @ T0, 50.0, 500.0)
        assert err.value.code == "motion_failed"
        assert not engine.snapshot().moving  # still by the time the error arrives
        stopped = arm.tcp_pose()
        time.sleep(0.3)
        assert_still(stopped, arm.tcp_pose(), "after the failed move")
        assert 1.0 < pose_distance(stopped, T0)[0] < 100.0  # it had moved, then it stopped
        assert [c.kind for c in arm.commanded()] == ["move_linear", "stop"]
        with pytest.raises(RefusedError) as err:  # and nothing moves without the slot
            arm.move_linear(T0, 50.0, 500.0)
        assert err.value.code == "no_motion_slot"
    finally:
        engine.close()


def test_gripper_timeouts_do_not_slow_status_and_stops_are_not_moving(tmp_path: Path) -> None:
    """A gripper that times out on every request (up to 1 s each) does not slow /status."""
    with running_cell(sim_config(tmp_path, gripper="sim")) as cell:
        world(cell).inject_gripper_fault("no_answer", 1000)
        worst = 0.0
        start = time.monotonic()
        while True:  # two failed reads in a row make the fault: ~3 s of timeouts
            t0 = time.perf_counter()
            st = cell.status()
            worst = max(worst, time.perf_counter() - t0)
            if st["gripper"]["error"] and time.monotonic() - start > 2.0:
                break
            assert time.monotonic() - start < 15.0, st["gripper"]
            time.sleep(0.05)
        assert worst < 0.25, f"status took {worst:.3f} s"
        # a protective stop mid-jog: not "moving" once the arm has braked
        cell.jog_start("test", frame="base", linear_mm_s=[30.0, 0, 0], angular_deg_s=[0, 0, 0])
        time.sleep(0.2)
        world(cell).trigger_protective_stop("test")
        time.sleep(0.5)
        robot = cell.status()["robot"]
        assert robot["protective_stop"] and not robot["moving"]


def test_losing_the_camera_mid_approach_fails_it_at_once_and_stops_the_arm(
        tmp_path: Path) -> None:
    """The loss fails the approach when it happens, not at the next locate (1.7 s later)."""
    with running_cell(sim_config(tmp_path)) as cell:
        world(cell).set_target(translation_T(60.0, 40.0, 0.0) @ world(cell).true_T_base_target())
        job = cell.approach("test", speed_mm_s=60.0)
        start = tcp(cell)
        deadline = time.monotonic() + 5.0
        while pose_distance(tcp(cell), start)[0] < 3.0:
            assert time.monotonic() < deadline, "the approach never started moving"
            time.sleep(0.01)
        t_lost = time.monotonic()
        world(cell).set_camera_lost(True)
        while not cell.job(job.id).finished:
            assert time.monotonic() - t_lost < 2.0
            time.sleep(0.01)
        ended = cell.job(job.id)
        assert ended.state == "failed" and ended.error_code == "camera_lost", ended
        assert time.monotonic() - t_lost < 1.0
        stopped = tcp(cell)
        time.sleep(0.3)
        assert_still(stopped, tcp(cell), "after the camera loss")
        world(cell).set_camera_lost(False)
        deadline = time.monotonic() + 5.0
        while not cell.health()["camera_connected"]:
            assert time.monotonic() < deadline, "the camera never came back"
            time.sleep(0.05)


def test_stop_cancels_any_motion_and_refusals_are_audited(tmp_path: Path) -> None:
    with running_cell(sim_config(tmp_path)) as cell:
        cell.jog_start("test", frame="base", linear_mm_s=[0, 20.0, 0], angular_deg_s=[0, 0, 0])
        stopper = threading.Thread(target=cell.stop, args=("test",))
        stopper.start()
        stopper.join(5.0)
        deadline = time.monotonic() + 2.0
        while cell.core.slot.current is not None:
            assert time.monotonic() < deadline
            time.sleep(0.01)
        with pytest.raises(CellError):
            cell.heartbeat("test")
        rows = [e.outcome for e in cell.jobs.audit_log(50)]
        assert "ok" in rows


def test_joint_moves_are_checked_along_their_path(tmp_path: Path) -> None:
    """Home is a joint move: its path, through the arm's kinematics, must stay in the box."""
    with running_cell(sim_config(tmp_path)) as cell:
        home = cell.arm.state().T_base_tcp.copy()
        cell.jog_step("test", frame="base", translation_mm=[0, 80.0, -60.0],
                      rotation_deg=[0, 0, 20.0])
        job = cell.home("test", wait=True)
        assert job.state == "succeeded", job.error_message
        assert pose_distance(settled_tcp(cell), home)[0] < 0.5
        joint = [c for c in cell.commanded() if c.kind == "move_joint"]
        assert joint and len(joint[-1].path) >= 3
        assert_paths_within(cell.commanded(), cell.arm.guard)
        # a home outside the (tightened) box is refused and nothing moves
        cell.jog_step("test", frame="base", translation_mm=[0, 0, 50.0], rotation_deg=[0, 0, 0])
        low = cell.config.limits.model_copy(update={"workspace_min_mm": (
            *cell.config.limits.workspace_min_mm[:2], float(home[2, 3]) + 10.0)})
        cell.arm.guard = SafetyGuard(LimitsConfig.model_validate(low.model_dump()))
        before = tcp(cell)
        with pytest.raises(CellError) as err:
            cell.home("test", wait=True)
        assert err.value.code == "outside_envelope"
        assert_still(before, tcp(cell), "refused home")
