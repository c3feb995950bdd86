"""The controller's own watchdog: a frozen ur_rtde child or a frozen host process stops the arm.

The arm's state is read from the simulated controller itself (its engine), not through the
adapter that is being frozen.
"""

from __future__ import annotations

import math
import os
import signal
import subprocess
import sys
import textwrap
import time

import numpy as np
import pytest

from drivers.ur.adapter import URArm
from fakes.ur_controller.process import ControllerProcess

pytestmark = pytest.mark.timeout(90)
SPEED_MM_S = 50.0
# generous for a loaded 2-core host; the benchmark (cell bench freeze) measures the real figure
STILL_WITHIN_S = 1.0
TRAVEL_WITHIN_MM = 40.0


def controller_still_after(ctl: ControllerProcess, t_freeze: float,
                           p_freeze: np.ndarray) -> tuple[float, float]:
    """Poll the controller's own state until its TCP stops: (seconds after the freeze,
    mm travelled since the freeze)."""
    deadline = t_freeze + 5.0
    last = np.asarray(ctl.state()["tcp_pose"][:3])
    last_t = time.monotonic()
    while time.monotonic() < deadline:
        time.sleep(0.02)
        p = np.asarray(ctl.state()["tcp_pose"][:3])
        now = time.monotonic()
        if np.linalg.norm(p - last) / (now - last_t) < 1e-4:  # under 0.1 mm/s
            return last_t - t_freeze, 1000.0 * float(np.linalg.norm(last - p_freeze))
        last, last_t = p, now
    return math.inf, 1000.0 * float(np.linalg.norm(last - p_freeze))


def test_frozen_client_process_stops_the_arm_mid_jog() -> None:
    with ControllerProcess(powered=True) as ctl:
        arm = URArm(ctl.host)
        arm.connect()
        try:
            arm.power_on()
            arm.jog(np.array([SPEED_MM_S, 0, 0, 0, 0, 0.0]), "base", 500.0)
            time.sleep(0.3)
            child = arm._client
            assert child is not None
            p0 = np.asarray(ctl.state()["tcp_pose"][:3])
            t0 = time.monotonic()
            os.kill(child._proc.pid, signal.SIGSTOP)
            try:
                still_s, moved_mm = controller_still_after(ctl, t0, p0)
            finally:
                os.kill(child._proc.pid, signal.SIGCONT)
            assert still_s < STILL_WITHIN_S and moved_mm < TRAVEL_WITHIN_MM, (still_s, moved_mm)
            messages = ctl.state()["messages"]
            assert any("watchdog" in m for m in messages), messages
        finally:
            arm.disconnect()


_HOST_SCRIPT = textwrap.dedent("""
    import sys, time
    import numpy as np
    from drivers.ur.adapter import URArm
    arm = URArm(sys.argv[1])
    arm.connect()
    arm.power_on()
    print("child", arm._client._proc.pid, flush=True)
    while True:  # a servo-like stream of twists, as the cell sends them
        arm.servo_twist(np.array([50.0, 0, 0, 0, 0, 0]), 500.0, 0.25)
        time.sleep(0.02)
""")


def test_frozen_host_process_stops_the_arm_and_its_child_dies_with_it() -> None:
    with ControllerProcess(powered=True) as ctl:
        host = subprocess.Popen([sys.executable, "-c", _HOST_SCRIPT, ctl.host],
                                stdout=subprocess.PIPE, text=True)
        try:
            assert host.stdout is not None
            line = host.stdout.readline()
            child_pid = int(line.split()[1])
            time.sleep(0.5)
            p0 = np.asarray(ctl.state()["tcp_pose"][:3])
            t0 = time.monotonic()
            os.kill(host.pid, signal.SIGSTOP)
            still_s, moved_mm = controller_still_after(ctl, t0, p0)
            assert still_s < STILL_WITHIN_S and moved_mm < TRAVEL_WITHIN_MM, (still_s, moved_mm)
            os.kill(host.pid, signal.SIGKILL)
            host.wait(timeout=5.0)
            deadline = time.monotonic() + 5.0
            while time.monotonic() < deadline:
                try:
                    os.kill(child_pid, 0)
                except ProcessLookupError:
                    break
                time.sleep(0.05)
            else:
                pytest.fail("the ur_rtde child outlived its parent")
        finally:
            if host.poll() is None:
                host.kill()


def test_ctrl_c_does_not_reach_the_client_process() -> None:
    with ControllerProcess(powered=True) as ctl:
        arm = URArm(ctl.host)
        arm.connect()
        try:
            child = arm._client
            assert child is not None
            os.killpg(os.getpgid(os.getpid()), 0)  # we are in a group of our own making
            assert os.getpgid(child._proc.pid) != os.getpgid(os.getpid())
            os.kill(child._proc.pid, signal.SIGINT)  # even sent to it directly: ignored
            time.sleep(0.5)
            assert child._proc.poll() is None
            assert arm.state().connected
        finally:
            arm.disconnect()
