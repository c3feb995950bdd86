"""The gripper's link comes back without a restart: a gripper off at start is connected when it
answers, and a serial device that goes away and returns (an adapter re-plugged) is used again.

The gripper is the simulated Robotiq on a pseudo-terminal behind a fixed device path, driven by
the real Modbus RTU adapter, as the service drives it.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import pytest

from cell.jobs.audit import Auditor
from cell.jobs.events import EventBus
from cell.jobs.store import JobStore
from cell.stats import CellStats
from cell.supervision.gripper import GripperService
from drivers.robotiq import RobotiqGripper
from fakes.gripper import FakeGripper

WAIT_S = 15.0  # a loaded host: the poll runs every 0.5 s, a failing connect takes ~1 s


@pytest.fixture
def link(tmp_path: Path) -> Path:
    return tmp_path / "ttyGRIPPER"


@pytest.fixture
def service(tmp_path: Path, link: Path) -> Iterator[GripperService]:
    store = JobStore(tmp_path / "jobs.db")
    svc = GripperService(RobotiqGripper(str(link), timeout_s=0.3, retries=0),
                         Auditor(store, CellStats()), EventBus())
    yield svc
    svc.close()
    assert svc.gripper is not None
    svc.gripper.disconnect()


def wait_for(what: str, check: Callable[[dict[str, Any]], bool],
             service: GripperService) -> dict[str, Any]:
    deadline = time.monotonic() + WAIT_S
    while True:
        st = service.status()
        assert st is not None
        if check(st):
            return st
        assert time.monotonic() < deadline, f"{what}: last status {st}"
        time.sleep(0.05)


def test_a_gripper_off_at_start_is_connected_when_it_answers(
        link: Path, service: GripperService) -> None:
    service.start()
    st = service.status()
    assert st is not None and st["error"] is not None
    with FakeGripper(link, activation_time_s=0.2):
        up = wait_for("connected", lambda s: s["error"] is None and s.get("activated"), service)
        assert up["position_mm"] == 85.0
        assert service.command("test", "close")["position_mm"] == 0.0


def test_a_device_that_goes_away_and_returns_is_used_again(
        link: Path, service: GripperService) -> None:
    with FakeGripper(link, activation_time_s=0.2):
        service.start()
        wait_for("connected", lambda s: s["error"] is None and s.get("activated"), service)
    wait_for("the loss seen", lambda s: s["error"] is not None, service)
    with FakeGripper(link, activation_time_s=0.2):
        wait_for("the link back", lambda s: s["error"] is None, service)
        # a re-plugged gripper lost its power too: the operator activates it, then it moves
        assert not service.status()["activated"]  # type: ignore[index]
        service.command("test", "activate")
        assert service.command("test", "close")["position_mm"] == 0.0


def test_a_read_that_failed_after_the_service_was_held_still_says_so(
        tmp_path: Path, link: Path) -> None:
    # the gripper goes quiet right after a stall the host watch saw: the fault names both
    store = JobStore(tmp_path / "jobs2.db")
    seen: list[float] = []

    def host_note(since_s: float) -> str | None:
        seen.append(since_s)
        return "the host did not let this service run for 0.80 s"

    svc = GripperService(RobotiqGripper(str(link), timeout_s=0.3, retries=0),
                         Auditor(store, CellStats()), EventBus(), host_note=host_note)
    try:
        with FakeGripper(link, activation_time_s=0.2) as fake:
            svc.start()
            wait_for("connected", lambda s: s["error"] is None and s.get("activated"), svc)
            fake.inject_line_fault("no_answer", count=1000)
            st = wait_for("the silence seen", lambda s: s["error"] is not None, svc)
        assert "no answer from gripper" in st["error"], st
        assert "(the host did not let this service run for 0.80 s)" in st["error"], st
        assert seen and time.monotonic() - 10.0 < seen[-1] < time.monotonic(), seen
    finally:
        svc.close()
        assert svc.gripper is not None
        svc.gripper.disconnect()


def test_one_missed_background_read_is_counted_two_in_a_row_are_a_fault(
        link: Path, service: GripperService) -> None:
    with FakeGripper(link, activation_time_s=0.2) as fake:
        service.start()
        wait_for("connected", lambda s: s["error"] is None and s.get("activated"), service)
        events = service.events.subscribe()
        fake.inject_line_fault("no_answer", count=1)
        deadline = time.monotonic() + WAIT_S
        while service.missed_reads < 1:
            assert time.monotonic() < deadline, "the missed read was not counted"
            time.sleep(0.05)
        wait_for("a read after it", lambda s: s["age_s"] is not None and s["age_s"] < 0.4,
                 service)
        assert service.status()["error"] is None  # type: ignore[index]
        assert events.get(0.0) is None  # no gripper event: nothing was published
        fake.inject_line_fault("no_answer", count=1000)
        st = wait_for("the silence seen", lambda s: s["error"] is not None, service)
        assert "no answer from gripper" in st["error"] and service.missed_reads >= 3, st
