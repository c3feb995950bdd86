"""A frozen host mid-servo leaves the arm still: ``cell serve`` on the simulated cell through
ur_rtde, tracking (``POST /track``) or servoing an approach (``POST /approach``, mode servo),
and either its ur_rtde child or the whole service process is frozen with SIGSTOP.

The arm is judged by the simulated controller itself, read by an independent RTDE receive
client in this process (the controller's own clock and TCP), not through the frozen service.
After SIGCONT the service recovers without a restart: it homes again.
"""

from __future__ import annotations

import contextlib
import csv
import os
import signal
import subprocess
import sys
import time
import tomllib
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import httpx
import numpy as np
import pytest

from estimator.transforms import pose_dict
from tests.cell.commands.test_serve_ctrl_c import _config
from tests.cell.test_servo_ur import HOME_TARGET
from tests.support.cell import AUTH
from tests.support.net import free_port

rtde_receive = pytest.importorskip("rtde_receive")
pytestmark = pytest.mark.timeout(240)

# From the freeze to the controller's TCP standing (controller clock), and the travel meanwhile.
# The product's figures (0.25 s and 10 mm at 50 mm/s, met with 154 ms / 7.4 mm at load 12) are
# measured by `cell bench freeze`; here the bound is what a loaded 2-core host running the whole
# suite beside the simulated controller still holds (measured: up to 0.30 s, 10.3 mm), far from
# the 2 s / 100 mm the arm ran without the controller's watchdog.
STILL_WITHIN_S = 0.5
TRAVEL_WITHIN_MM = 20.0
STILL_SPEED_MM_S = 0.5
SPEED_MM_S = 50.0  # the servo's speed cap here, and the conveyor's speed


@dataclass
class Service:
    proc: subprocess.Popen[str]
    url: str
    robot_host: str
    log: Path

    def post(self, path: str, body: dict[str, Any] | None = None, role: str = "operator",
             timeout_s: float = 30.0) -> httpx.Response:
        return httpx.post(f"{self.url}{path}", json=body or {}, headers=AUTH[role],
                          timeout=timeout_s)

    def get(self, path: str) -> Any:
        r = httpx.get(f"{self.url}{path}", headers=AUTH["viewer"], timeout=30.0)
        assert r.status_code == 200, r.text
        return r.json()

    def child_pid(self) -> int:
        """The service's ur_rtde child (``python -m drivers.ur.client_process``)."""
        for entry in Path("/proc").iterdir():
            if not entry.name.isdigit():
                continue
            try:
                ppid = int((entry / "stat").read_text().rsplit(")", 1)[1].split()[1])
                cmd = (entry / "cmdline").read_bytes()
            except (OSError, IndexError, ValueError):
                continue
            if ppid == self.proc.pid and b"drivers.ur.client_process" in cmd:
                return int(entry.name)
        raise AssertionError("the service has no ur_rtde child")


@pytest.fixture(scope="module")
def service(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Service]:
    tmp = tmp_path_factory.mktemp("servo_freeze")
    config = _config(tmp)
    text = config.read_text()
    robot_host = str(tomllib.loads(text)["robot"]["host"])
    # a slow servo (the frozen arm's travel scales with its speed); loss of the target on a
    # loaded host is not what these tests are about, so the lost-target clock is generous
    config.write_text(text + f"\n[servo]\nmax_speed_mm_s = {SPEED_MM_S}\nlost_after_s = 1.0\n"
                      "stall_after_s = 5.0\n")
    port = free_port()
    log = tmp / "serve.log"
    with log.open("w") as out:
        proc = subprocess.Popen(
            [sys.executable, "-m", "cell", "serve", "--config", str(config), "--port",
             str(port)], stdout=out, stderr=subprocess.STDOUT, text=True,
            start_new_session=True)
    svc = Service(proc, f"http://127.0.0.1:{port}/api/v1", robot_host, log)
    try:
        deadline = time.monotonic() + 90
        while True:
            assert proc.poll() is None, log.read_text()[-3000:]
            try:
                r = httpx.get(f"{svc.url}/health", timeout=1)
                if r.status_code == 200 and r.json().get("status") == "ok":
                    break
            except httpx.TransportError:
                pass
            assert time.monotonic() < deadline, "the service did not become healthy in 90 s"
            time.sleep(0.3)
        yield svc
    finally:
        os.killpg(proc.pid, signal.SIGCONT)
        os.killpg(proc.pid, signal.SIGINT)
        try:
            proc.wait(timeout=30)
        except subprocess.TimeoutExpired:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait()


@pytest.fixture(scope="module")
def receiver(service: Service) -> Iterator[Any]:
    r = rtde_receive.RTDEReceiveInterface(service.robot_host)
    yield r
    r.disconnect()


def _speed_mm_s(r: Any) -> float:
    return 1000.0 * float(np.linalg.norm(np.asarray(r.getActualTCPSpeed())[:3]))


def _place(svc: Service, x_offset_mm: float = 0.0, velocity_mm_s: float = 0.0) -> None:
    T = HOME_TARGET.copy()
    T[0, 3] += x_offset_mm
    body: dict[str, Any] = {**pose_dict(T), "velocity_mm_s": [-velocity_mm_s, 0.0, 0.0]}
    r = httpx.put(f"{svc.url}/sim/target", json=body, headers=AUTH["operator"], timeout=30)
    assert r.status_code == 200, r.text


def _home(svc: Service) -> None:
    svc.post("/stop", role="viewer")
    _place(svc)
    deadline = time.monotonic() + 60
    while True:  # after a freeze the first motion may meet a script the controller ended
        r = svc.post("/arm/home", {"wait": True}, timeout_s=60)
        if r.status_code == 200 and r.json()["state"] == "succeeded":
            return
        assert time.monotonic() < deadline, r.text
        time.sleep(0.5)


def _wait_moving(r: Any, job: Any, svc: Service, timeout_s: float = 30.0) -> None:
    deadline = time.monotonic() + timeout_s
    while _speed_mm_s(r) < 0.5 * SPEED_MM_S:
        state = svc.get(f"/jobs/{job}")
        assert state["state"] == "running", (state["error"], svc.log.read_text()[-4000:])
        assert time.monotonic() < deadline, "the arm never reached speed"
        time.sleep(0.01)


def _moving(svc: Service, r: Any, motion: str) -> str:
    """Home, start ``motion`` and wait until the arm runs at speed: the job's id. A start that
    a loaded host lets fail before the freeze is not what these tests judge; it is started
    again (up to twice): the controller's answer later than the client's 3 s deadline (the
    job ends ``arm_disconnected``), the controller's own watchdog ending the control script
    of a starved host (``motion_failed``: "speedL was rejected"), or a host held so long that
    the conveyor carried the target out of view before the arm reached speed
    (``target_lost``), the arm still each way."""
    attempts = 3
    for attempt in range(attempts):
        _home(svc)
        job = _start(svc, motion)
        try:
            _wait_moving(r, job, svc)
            return job
        except AssertionError as err:
            retried = ("arm_disconnected", "motion_failed", "target_lost")
            if attempt == attempts - 1 or not any(code in str(err) for code in retried):
                raise
            print(f"start failed before the freeze, started again: {str(err)[:300]}")
            deadline = time.monotonic() + 2.0  # the controller's watchdog stops the arm
            while _speed_mm_s(r) >= STILL_SPEED_MM_S:
                assert time.monotonic() < deadline, "the arm ran on after its client died"
                time.sleep(0.01)
    raise AssertionError("unreachable")


def _recorded(path: Path) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(controller timestamps s, TCP positions m, TCP linear speeds mm/s) of a recording."""
    with path.open() as f:
        rows = list(csv.DictReader(f))
    t = np.array([float(r["timestamp"]) for r in rows])
    p = np.array([[float(r[f"actual_TCP_pose_{i}"]) for i in range(3)] for r in rows])
    v = np.array([[float(r[f"actual_TCP_speed_{i}"]) for i in range(3)] for r in rows])
    return t, p, 1000.0 * np.linalg.norm(v, axis=1)


def _still_after_freeze(r: Any, pid: int, tmp: Path) -> tuple[float, float]:
    """Freeze ``pid``; from every package of the controller's own stream (ur_rtde records
    them in its own thread, so this process's scheduling does not blur the figure):
    (controller seconds from the freeze to the TCP standing, mm travelled meanwhile). The
    process is thawed afterwards."""
    rec = tmp / f"freeze-{pid}-{time.monotonic_ns()}.csv"
    r.startFileRecording(str(rec), ["timestamp", "actual_TCP_pose", "actual_TCP_speed"])
    time.sleep(0.1)
    t_ctl0 = float(r.getTimestamp())  # the controller's clock when the freeze is sent
    os.kill(pid, signal.SIGSTOP)
    try:
        deadline = time.monotonic() + 10.0
        while time.monotonic() < deadline and _speed_mm_s(r) >= STILL_SPEED_MM_S:
            time.sleep(0.01)  # poll until the controller's TCP stands
        time.sleep(0.1)
    finally:
        r.stopFileRecording()
        time.sleep(0.4)  # frozen well past the watchdog's reach
        # the service may have given up on (and replaced) a child that did not answer
        with contextlib.suppress(ProcessLookupError):
            os.kill(pid, signal.SIGCONT)
    t, p, v = _recorded(rec)
    after = t >= t_ctl0
    i0 = int(np.argmax(after))
    still = np.nonzero(after & (v < STILL_SPEED_MM_S))[0]
    if not len(still):
        return float("inf"), 1000.0 * float(np.linalg.norm(p[-1] - p[i0]))
    k = int(still[0])
    return float(t[k] - t[i0]), 1000.0 * float(np.linalg.norm(p[k] - p[i0]))


def _start(svc: Service, motion: str) -> str:
    if motion == "track":
        r = svc.post("/track", {"standoff_mm": 50, "duration_s": 60}, role="plc")
        assert r.status_code == 200, r.text
        job = r.json()["id"]
        time.sleep(1.5)  # the arm holds the still target
        _place(svc, velocity_mm_s=SPEED_MM_S)  # then it drifts along -x
        return str(job)
    _place(svc, x_offset_mm=60.0)  # far enough for the approach to run at its speed cap
    time.sleep(0.2)
    r = svc.post("/approach", {"standoff_mm": 50, "mode": "servo"}, role="plc")
    assert r.status_code == 200, r.text
    return str(r.json()["id"])


@pytest.mark.parametrize("motion", ["track", "servo_approach"])
@pytest.mark.parametrize("frozen", ["ur_rtde_child", "service"])
def test_frozen_host_mid_servo_leaves_the_arm_still(service: Service, receiver: Any,
                                                   motion: str, frozen: str,
                                                   tmp_path: Path) -> None:
    job = _moving(service, receiver, motion)
    pid = service.child_pid() if frozen == "ur_rtde_child" else service.proc.pid
    still_s, moved_mm = _still_after_freeze(receiver, pid, tmp_path)
    assert still_s <= STILL_WITHIN_S and moved_mm <= TRAVEL_WITHIN_MM, (still_s, moved_mm)
    # the service goes on after the thaw: a stop ends the job with the arm still, and the
    # next motion runs without a restart
    assert service.post("/stop", role="viewer").status_code == 200
    deadline = time.monotonic() + 30
    while service.get(f"/jobs/{job}")["state"] == "running":
        assert time.monotonic() < deadline, service.get(f"/jobs/{job}")
        time.sleep(0.1)
    time.sleep(0.3)
    assert _speed_mm_s(receiver) < STILL_SPEED_MM_S
    _home(service)
