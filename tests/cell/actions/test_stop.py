"""STOP on a fast simulated cell: the gripper's part of the answer, and the gate's order.

The races against the real ur_rtde client on a loaded host are in
tests/realtime/test_stop_race.py; these are the rules those races rely on, each shown once.
"""

from __future__ import annotations

import contextlib
import threading
import time
from collections.abc import Iterator
from pathlib import Path

import pytest

from cell.errors import Cancelled
from cell.motion.guard import CommandGate, Motion
from cell.service import Cell
from drivers.errors import DeviceTimeoutError
from tests.support.cell import running_cell, sim_config
from tests.support.waiting import wait_until


@pytest.fixture
def cell(tmp_path: Path) -> Iterator[Cell]:
    with running_cell(sim_config(tmp_path, gripper="sim")) as c:
        wait_until(lambda: (c.gripper_ops.status() or {}).get("activated"), 10.0,
                   "the gripper activated")
        yield c


def test_a_stop_halts_the_fingers_and_ends_the_gripper_command_cancelled(cell: Cell) -> None:
    cell.gripper("test", "open")
    ended: list[BaseException | None] = []

    def close() -> None:
        try:
            cell.gripper("test", "move", position_mm=0.0, speed_pct=0.0)  # 4 s to close
            ended.append(None)
        except BaseException as err:
            ended.append(err)

    t = threading.Thread(target=close)
    t.start()
    wait_until(lambda: cell.core.slot.current is not None, 5.0, "the close to hold the slot")
    time.sleep(0.3)
    answer = cell.stop("test")
    t.join(10.0)
    assert answer["stopped"] is True and answer["cancelled"] == "gripper", answer
    assert len(ended) == 1 and isinstance(ended[0], Cancelled), ended
    g = cell.hw.gripper
    assert g is not None
    first = g.status().position_mm
    time.sleep(0.3)
    assert abs(g.status().position_mm - first) < 0.5 and first > 60.0


def test_a_gripper_that_cannot_be_halted_makes_the_stop_answer_not_stopped(
        cell: Cell, monkeypatch: pytest.MonkeyPatch) -> None:
    g = cell.hw.gripper
    assert g is not None
    cell.gripper("test", "open")
    started = threading.Event()

    def close() -> None:
        with cell.core.slot.hold("close"):
            started.set()
            with contextlib.suppress(Cancelled):  # the stop reached it, the fingers did not
                cell.gripper_ops.command("test", "move", position_mm=0.0, speed_pct=0.0,
                                         motion=cell.core.slot.current)

    def silent() -> None:
        raise DeviceTimeoutError("no answer from the gripper")

    t = threading.Thread(target=close)
    t.start()
    assert started.wait(5.0)
    wait_until(lambda: g.status().moving, 5.0, "the fingers moving")
    monkeypatch.setattr(g, "stop", silent)
    answer = cell.stop("test")
    monkeypatch.undo()
    t.join(10.0)
    assert answer["stopped"] is False and "no answer" in str(answer.get("gripper_error")), answer
    assert answer["arm_error"] is None


def test_a_command_that_passed_the_gate_before_the_stop_is_sent_before_it() -> None:
    """The gate's order: a stop waits for a command already past its check, and a command
    that comes to the gate after the flag is set is never sent."""
    gate, order = CommandGate(), []
    motion = Motion("test")
    inside = threading.Event()

    def command() -> None:
        with gate.command(motion, "move"):
            inside.set()
            time.sleep(0.2)  # the send, on a slow host
            order.append("move sent")

    t = threading.Thread(target=command)
    t.start()
    assert inside.wait(5.0)
    motion.cancel_with()
    with gate.stopping():
        order.append("stop sent")
    t.join(5.0)
    assert order == ["move sent", "stop sent"]
    with pytest.raises(Cancelled), gate.command(motion, "move"):
        order.append("never")
    assert order == ["move sent", "stop sent"]
