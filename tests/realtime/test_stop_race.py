"""STOP raced against the start of every kind of motion, on a loaded host.

The invariant: once STOP has answered ``stopped: true``, no motion the cell commanded before
or during the STOP goes on (the arm brakes and stands; the fingers halt), and what owned the
motion ends ``cancelled``. Each race claims the motion slot, starts a motion (a joint move, a
straight move, a stream of servo twists, a gripper close, the home job) and sends STOP after a
random delay between nothing and well past the move's first controller cycle, so the stop
lands before the command, while it is on its way, and after it started. The simulated UR
controller is driven through the real ur_rtde client, the gripper through the real Modbus RTU
adapter, with two CPU-burning processes beside them. Outcomes are the simulator's truth.
"""

from __future__ import annotations

import random
import threading
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest

from cell.errors import Cancelled, CellError
from cell.jobs.store import Job
from cell.service import Cell
from estimator.transforms import pose_distance
from fakes.ur_controller.load import cpu_burners
from fakes.ur_controller.process import free_loopback_host
from tests.support.cell import running_cell, sim_config, standing_tcp, tcp
from tests.support.waiting import wait_until

MAX_DELAY_S = 0.15  # past the first controller cycle even when the host delays the command
STILL_MM = 0.02  # two reads this close, 0.1 s apart: the arm stands
SEED = 20261203


@pytest.fixture(scope="module")
def cell(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Cell]:
    tmp: Path = tmp_path_factory.mktemp("stop_race")
    # the simulated gripper answers from a thread of this starved process, not from a device
    # of its own: its Modbus answers get a real gripper's margin back with a longer timeout
    config = sim_config(tmp, robot="ur", host=free_loopback_host(), gripper="sim")
    config = config.model_copy(update={"gripper": config.gripper.model_copy(
        update={"timeout_s": 2.0})})
    with cpu_burners(2, max_s=600.0), running_cell(config) as c:
        wait_until(lambda: c.arm_state().ready, 30.0, "the simulated arm ready")
        yield c


@dataclass
class Race:
    answer: dict[str, object]
    end: str  # how the mover ended: "cancelled", "done", or an error code
    T_at_answer: np.ndarray
    T_still: np.ndarray


def _race(cell: Cell, name: str, command: Callable[[], None], delay_s: float) -> Race:
    """``command`` run holding the slot in a thread; STOP ``delay_s`` after the claim."""
    claimed = threading.Event()
    ended: list[str] = []

    def mover() -> None:
        try:
            with cell.core.slot.hold(name):
                claimed.set()
                command()
            ended.append("done")
        except Cancelled:
            ended.append("cancelled")
        except CellError as err:
            ended.append(str(err.code))

    t = threading.Thread(target=mover, daemon=True)
    t.start()
    assert claimed.wait(10.0), "the mover never claimed the slot"
    time.sleep(delay_s)
    answer = cell.stop("race", reason=f"race {name} at {delay_s * 1000:.0f} ms")
    T_at_answer = tcp(cell)
    t.join(30.0)
    assert not t.is_alive(), f"the {name} did not end after the stop"
    return Race(answer, ended[0], T_at_answer, standing_tcp(cell, STILL_MM))


def _check(cell: Cell, race: Race, name: str, T_goal: np.ndarray, brake_mm: float) -> None:
    assert race.answer["stopped"] is True, race.answer
    assert race.answer["cancelled"] == name, race.answer
    assert race.end == "cancelled", f"the {name} ended {race.end!r} after the stop"
    after_mm = pose_distance(race.T_at_answer, race.T_still)[0]
    assert after_mm <= brake_mm, f"the arm went on {after_mm:.1f} mm after STOP answered"
    # short of the goal: a starved host may hand the stop over late, but never after the end
    assert pose_distance(race.T_still, T_goal)[0] > 1.0, "the move ran to its goal"
    time.sleep(0.2)
    assert pose_distance(race.T_still, tcp(cell))[0] < 0.05, \
        "the arm moved again after it had stopped"


def _ended(cell: Cell, job_id: str) -> Job | None:
    job = cell.job(job_id)
    return None if job.state == "running" else job


def _delays(n: int, seed: int) -> list[float]:
    """``n`` delays spread over [0, MAX_DELAY_S], the ends included, in a shuffled order."""
    rng = random.Random(seed)
    delays = list(np.linspace(0.0, MAX_DELAY_S, n))
    rng.shuffle(delays)
    return [float(d) for d in delays]


def test_stop_ends_a_joint_move_whatever_the_timing(cell: Cell) -> None:
    q_home = np.radians(cell.config.robot.home_joints_deg)
    q_away = q_home + np.radians([25.0, -10.0, 15.0, 0.0, 0.0, 0.0])
    speed, accel = np.radians(30.0), np.radians(60.0)
    for k, delay in enumerate(_delays(12, SEED)):
        q0 = cell.arm.joint_positions_rad()
        q1 = q_away if np.max(np.abs(q_away - q0)) > np.max(np.abs(q_home - q0)) else q_home
        T_goal = cell.arm.forward_kinematics(q1)
        race = _race(cell, "joint race", lambda q=q1: cell.arm.move_joint(
            q, speed, accel, what="race goal"), delay)
        try:
            _check(cell, race, "joint race", T_goal, brake_mm=25.0)
        except AssertionError as err:
            raise AssertionError(f"race {k} at {delay * 1000:.0f} ms: {err}") from err


def test_stop_ends_a_straight_move_whatever_the_timing(cell: Cell) -> None:
    T_home = cell.arm.forward_kinematics(np.radians(cell.config.robot.home_joints_deg))
    for k, delay in enumerate(_delays(12, SEED + 1)):
        T0 = cell.arm.tcp_pose()
        T_goal = T0.copy()
        # 120 mm along x, towards home's side so the arm stays near where it started
        T_goal[0, 3] += 120.0 if T0[0, 3] < T_home[0, 3] else -120.0
        race = _race(cell, "linear race", lambda T=T_goal: cell.arm.move_linear(
            T, 200.0, 1000.0, what="race goal"), delay)
        try:
            _check(cell, race, "linear race", T_goal, brake_mm=15.0)
        except AssertionError as err:
            raise AssertionError(f"race {k} at {delay * 1000:.0f} ms: {err}") from err


def test_stop_ends_a_stream_of_servo_twists_whatever_the_timing(cell: Cell) -> None:
    accel, watchdog_s = 1000.0, 0.1
    T_home = cell.arm.forward_kinematics(np.radians(cell.config.robot.home_joints_deg))
    for k, delay in enumerate(_delays(10, SEED + 2)):
        sign = 1.0 if tcp(cell)[1, 3] < T_home[1, 3] else -1.0

        def stream(sign: float = sign) -> None:
            v_mm_s, last = 0.0, time.monotonic()
            deadline = last + 3.0
            while time.monotonic() < deadline:  # ramps to 60 mm/s along y, ticks at ~125 Hz
                now = time.monotonic()
                v_mm_s = min(60.0, v_mm_s + 0.9 * accel * max(0.008, now - last))
                last = now
                cell.arm.servo_twist(np.array([0.0, sign * v_mm_s, 0, 0, 0, 0]), accel,
                                     watchdog_s)
                time.sleep(0.008)

        T_far = tcp(cell).copy()
        T_far[1, 3] += sign * 1000.0  # the stream never ends by itself within the race
        race = _race(cell, "servo race", stream, delay)
        try:
            _check(cell, race, "servo race", T_far, brake_mm=8.0)
        except AssertionError as err:
            raise AssertionError(f"race {k} at {delay * 1000:.0f} ms: {err}") from err


def test_stop_halts_a_gripper_close_whatever_the_timing(cell: Cell) -> None:
    g = cell.hw.gripper
    assert g is not None
    for k, delay in enumerate(_delays(8, SEED + 3)):
        cell.gripper("race", "open", wait=True)

        def close() -> None:  # slowest speed: 4 s from open to closed
            cell.gripper_ops.command("race", "move", position_mm=0.0, speed_pct=0.0,
                                     wait=True, motion=cell.core.slot.current)

        race = _race(cell, "gripper race", close, delay)
        where = f"race {k} at {delay * 1000:.0f} ms"
        assert race.answer["stopped"] is True and race.answer["cancelled"] == "gripper race", \
            (where, race.answer)
        assert race.end == "cancelled", (where, race.end)
        first = g.status().position_mm
        time.sleep(0.3)
        second = g.status().position_mm
        assert abs(second - first) < 0.5, f"{where}: the fingers moved on after STOP answered"
        assert second > 60.0, f"{where}: the fingers closed to {second:.1f} mm"


def test_stop_cancels_the_home_job_whatever_the_timing(cell: Cell) -> None:
    """The job that owned the motion ends cancelled (never succeeded), and the arm stands
    where the stop left it, short of home."""
    q_home = np.radians(cell.config.robot.home_joints_deg)
    T_home = cell.arm.forward_kinematics(q_home)
    q_away = q_home + np.radians([0.0, 12.0, -20.0, 8.0, 0.0, 0.0])
    for k, delay in enumerate(_delays(10, SEED + 4)):
        if pose_distance(tcp(cell), T_home)[0] < 60.0:  # set up: away from home, unraced
            with cell.core.slot.hold("set up"):
                cell.arm.move_joint(q_away, np.radians(60.0), np.radians(120.0))
        job = cell.home("race", speed_deg_s=30.0)
        time.sleep(delay)
        answer = cell.stop("race", reason=f"race home at {delay * 1000:.0f} ms")
        T_at_answer = tcp(cell)
        ended = wait_until(lambda j=job.id: _ended(cell, j), 30.0, f"job {job.id} to end")
        T_still = standing_tcp(cell, STILL_MM)
        where = f"race {k} at {delay * 1000:.0f} ms"
        assert answer["stopped"] is True and answer["cancelled"] == "home", (where, answer)
        assert ended.state == "cancelled", (where, ended.state, ended.error_message)
        after_mm = pose_distance(T_at_answer, T_still)[0]
        assert after_mm <= 25.0, f"{where}: the arm went on {after_mm:.1f} mm after STOP"
        assert pose_distance(T_still, T_home)[0] > 1.0, f"{where}: the home move ran to its end"
