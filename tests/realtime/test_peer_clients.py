"""The simulated controller and gripper through client code nobody here wrote.

ur_rtde's Python API called the way its shipped examples call it (move_async,
movel_path_with_blend, move_path_async, servoj, speedj, io, record_data, realtime_control;
the calls are written here, the example files are not copied), python-urx and
pyrobotiqgripper unmodified. The tests whose claim is about timing (the 500 Hz streams, the
controller's cycle stamps) run while two CPU-burning processes load the 2-core host; the
others on the suite's own load. Outcomes are checked against the simulator's ground truth
(the controller process's state).
"""

from __future__ import annotations

import contextlib
import csv
import math
import socket
import struct
import time
from collections.abc import Iterator
from concurrent.futures import Future, ThreadPoolExecutor
from pathlib import Path

import numpy as np
import pytest

from tests.support.waiting import wait_until

rtde_control = pytest.importorskip("rtde_control")
rtde_receive = pytest.importorskip("rtde_receive")
rtde_io = pytest.importorskip("rtde_io")
dashboard_client = pytest.importorskip("dashboard_client")

from fakes.gripper import FakeGripper  # noqa: E402
from fakes.ur_controller.load import cpu_burners  # noqa: E402
from fakes.ur_controller.process import ControllerProcess  # noqa: E402

HOME_Q = [0.0, -1.571, 1.571, -1.571, -1.571, 0.0]


@pytest.fixture
def loaded_host() -> Iterator[None]:
    """Two CPU-burning processes for the test (each ends by itself within 2 min)."""
    with cpu_burners(2, max_s=120.0):
        yield


class _SpareControllers:
    """Every test gets a fresh controller, started while the test before it ran: under the
    burners a controller took seconds to start, and 18 of those in a row were 40 % of the
    module's time. Each is a new process on its own address; none is ever reused."""

    def __init__(self) -> None:
        self._pool = ThreadPoolExecutor(1, thread_name_prefix="spare-controller")
        self._next: Future[ControllerProcess] | None = None

    def _start(self) -> Future[ControllerProcess]:
        return self._pool.submit(ControllerProcess, powered=True)

    def take(self) -> ControllerProcess:
        current = self._next or self._start()
        self._next = self._start()
        return current.result()

    def close(self) -> None:
        if self._next is not None:
            self._next.result().close()
        self._pool.shutdown()


@pytest.fixture(scope="module")
def spare_controllers() -> Iterator[_SpareControllers]:
    spares = _SpareControllers()
    try:
        yield spares
    finally:
        spares.close()


@pytest.fixture
def ctl(spare_controllers: _SpareControllers) -> Iterator[ControllerProcess]:
    with spare_controllers.take() as proc:
        assert wait_until(lambda: proc.state()["robot_mode"] == "RUNNING", 10.0)
        yield proc


@pytest.fixture
def rtde(ctl: ControllerProcess) -> Iterator[tuple]:
    r = rtde_receive.RTDEReceiveInterface(ctl.host)
    c = rtde_control.RTDEControlInterface(ctl.host)
    yield c, r
    c.stopScript()
    c.disconnect()
    r.disconnect()


def truth_q(ctl: ControllerProcess) -> np.ndarray:
    return np.array(ctl.state()["q"])


def truth_pose(ctl: ControllerProcess) -> np.ndarray:
    return np.array(ctl.state()["tcp_pose"])


def no_stop(ctl: ControllerProcess) -> None:
    st = ctl.state()
    assert st["safety_mode"] == "NORMAL", st["messages"][-3:]


# -- ur_rtde examples ---------------------------------------------------------------------------

def test_move_async_progress_and_steady(ctl: ControllerProcess, rtde: tuple) -> None:
    c, r = rtde
    q = r.getActualQ()
    target = list(q)
    target[0] += 0.6
    assert c.moveJ(target, 1.05, 1.4, True)
    assert wait_until(lambda: c.getAsyncOperationProgress() >= 0, 2.0)
    running = c.getAsyncOperationProgressEx()
    assert running.isAsyncOperationRunning()
    assert not c.isSteady()
    assert wait_until(lambda: c.getAsyncOperationProgress() < 0, 10.0)
    assert wait_until(c.isSteady, 2.0)
    assert np.allclose(truth_q(ctl), target, atol=1e-4)
    # a moveL interrupted by stopL, as the example does
    pose = r.getActualTCPPose()
    down = list(pose)
    down[2] -= 0.2
    assert c.moveL(down, 0.25, 1.2, True)
    assert wait_until(lambda: not c.isSteady(), 2.0)
    time.sleep(0.3)
    c.stopL(0.5)
    assert wait_until(lambda: c.getAsyncOperationProgress() < 0 and c.isSteady(), 5.0)
    z = truth_pose(ctl)[2]
    assert down[2] + 0.01 < z < pose[2] - 0.01  # stopped part of the way down
    no_stop(ctl)


def test_movel_path_with_blend(ctl: ControllerProcess, rtde: tuple) -> None:
    c, r = rtde
    p0 = np.array(r.getActualTCPPose())
    a, b = p0.copy(), p0.copy()
    a[1] -= 0.15
    b[1] -= 0.15
    b[2] -= 0.15
    velocity, acceleration, blend = 0.5, 4.0, 0.05
    path = [[*a, velocity, acceleration, blend], [*b, velocity, acceleration, blend],
            [*p0, velocity, acceleration, 0.0]]
    t0 = time.monotonic()
    assert c.moveL(path)
    assert time.monotonic() - t0 > 0.6  # ~0.45 m of path at 0.5 m/s
    assert np.allclose(truth_pose(ctl), p0, atol=1e-4)
    no_stop(ctl)


def test_move_path_async_with_movej_to_tcp_poses(ctl: ControllerProcess, rtde: tuple) -> None:
    c, r = rtde
    p0 = np.array(r.getActualTCPPose())
    p1, p2 = p0.copy(), p0.copy()
    p1[0] += 0.1
    p2[2] -= 0.1
    path = rtde_control.Path()
    for pose, kind in ((p1, rtde_control.PathEntry.MoveJ), (p2, rtde_control.PathEntry.MoveL),
                       (p1, rtde_control.PathEntry.MoveJ)):
        path.addEntry(rtde_control.PathEntry(kind, rtde_control.PathEntry.PositionTcpPose,
                                             [*pose, 0.5, 1.0, 0.0]))
    assert c.movePath(path, True)
    seen = set()
    deadline = time.monotonic() + 15.0
    while time.monotonic() < deadline:
        progress = c.getAsyncOperationProgress()
        if progress < 0 and seen:
            break
        if progress >= 0:
            seen.add(progress)
        time.sleep(0.01)
    assert seen >= {0, 2}, seen
    # movej(p[...]) goes to the pose, not to "joint angles" equal to the pose's numbers
    assert np.allclose(truth_pose(ctl), p1, atol=1e-4)
    no_stop(ctl)


def test_servoj_stream_at_500_hz(ctl: ControllerProcess, rtde: tuple, loaded_host: None) -> None:
    c, r = rtde
    velocity, acceleration, dt, lookahead_time, gain = 0.5, 0.5, 1.0 / 500, 0.1, 300
    joint_q = list(r.getActualQ())
    assert c.moveJ(joint_q)
    for _ in range(1000):  # 2 s
        t_start = c.initPeriod()
        c.servoJ(joint_q, velocity, acceleration, dt, lookahead_time, gain)
        joint_q[0] += 0.001
        joint_q[1] += 0.001
        c.waitPeriod(t_start)
    c.servoStop()  # brakes from 0.5 rad/s at 10 rad/s^2: about 12 mrad past the last target
    assert wait_until(c.isSteady, 3.0)
    no_stop(ctl)
    last = np.array(joint_q) - np.array([0.001, 0.001, 0, 0, 0, 0])
    assert np.allclose(truth_q(ctl), last, atol=0.03)


def test_speedj_then_speed_stop(ctl: ControllerProcess, rtde: tuple) -> None:
    c, _r = rtde
    q0 = truth_q(ctl)
    joint_speed = [0.0, 0.0, 0.0, 0.0, 0.0, 0.0]
    for _ in range(500):  # ramps joint 5 by 0.0005 rad/s per cycle for 1 s
        t_start = c.initPeriod()
        c.speedJ(joint_speed, 0.5, 1.0 / 500)
        joint_speed[5] += 0.0005
        c.waitPeriod(t_start)
    c.speedStop()
    assert wait_until(c.isSteady, 3.0)
    moved = truth_q(ctl) - q0
    assert 0.05 < moved[5] < 0.4  # ~0.125 rad ramping to 0.25 rad/s, plus the braking
    assert np.allclose(moved[:5], 0.0, atol=1e-6)
    no_stop(ctl)


def test_io_and_speed_slider(ctl: ControllerProcess) -> None:
    io = rtde_io.RTDEIOInterface(ctl.host)
    r = rtde_receive.RTDEReceiveInterface(ctl.host)
    try:
        assert io.setStandardDigitalOut(7, True)
        assert io.setToolDigitalOut(0, True)
        assert io.setAnalogOutputVoltage(0, 0.5)
        assert io.setSpeedSlider(0.5)
        assert wait_until(lambda: r.getDigitalOutState(7) and r.getDigitalOutState(16), 2.0)
        assert wait_until(lambda: abs(r.getSpeedScaling() - 0.5) < 1e-9, 2.0)
        assert abs(r.getStandardAnalogOutput0() - 0.5) < 1e-9
        assert io.setStandardDigitalOut(7, False)
        assert wait_until(lambda: not r.getDigitalOutState(7), 2.0)
    finally:
        io.disconnect()
        r.disconnect()


def test_io_example_back_to_back_writes_land_in_the_same_few_cycles(
        ctl: ControllerProcess) -> None:
    """io_example sets a standard and a tool output one call after the other and reads both
    back 10 ms later. Each write is its own RTDE data package; the controller applies inputs
    every 2 ms cycle, so both show within a few cycles of each other (in controller time, so
    a stalled poller cannot make this pass or fail: a stall only shrinks the gap)."""
    io = rtde_io.RTDEIOInterface(ctl.host)
    r = rtde_receive.RTDEReceiveInterface(ctl.host)
    try:
        for level in (True, False, True):
            assert io.setStandardDigitalOut(7, level)
            assert io.setToolDigitalOut(0, level)
            seen: dict[int, float] = {}
            deadline = time.monotonic() + 5.0
            while len(seen) < 2 and time.monotonic() < deadline:
                stamp = r.getTimestamp()
                for bit in (7, 16):
                    if bit not in seen and r.getDigitalOutState(bit) == level:
                        seen[bit] = stamp
                time.sleep(0.0005)
            assert len(seen) == 2, seen
            assert abs(seen[16] - seen[7]) < 0.010, seen  # was 0.042 s: delayed TCP ACKs
    finally:
        io.disconnect()
        r.disconnect()


def test_record_data_timestamps_are_the_controllers_500_hz(ctl: ControllerProcess,
                                                           tmp_path: Path,
                                                           loaded_host: None) -> None:
    r = rtde_receive.RTDEReceiveInterface(ctl.host, 500.0)
    out = tmp_path / "robot_data.csv"
    try:
        assert r.startFileRecording(str(out), ["timestamp", "actual_q"])
        time.sleep(2.0)
        assert r.stopFileRecording()
    finally:
        r.disconnect()
    with out.open() as f:
        stamps = np.array([float(row["timestamp"]) for row in csv.DictReader(f)])
    assert len(np.unique(stamps)) > 50
    steps = np.diff(stamps) / 0.002
    # ur_rtde's recorder samples the latest package at its own pace (rows repeat or skip on a
    # loaded client), but every timestamp is a controller cycle, 2 ms apart, never backwards
    assert np.allclose(steps, np.round(steps), atol=1e-6)
    assert np.all(steps >= -1e-6)


def test_rtde_stream_every_cycle_under_load(ctl: ControllerProcess, loaded_host: None) -> None:
    """On the wire (RTDE guide: 'V' negotiation, 'O' setup, 'S' start, 'U' data), one data
    package per 2 ms controller cycle while the host is loaded."""
    from fakes.ur_controller import rtde as wire

    with socket.create_connection((ctl.host, 30004), timeout=3.0) as s:
        reader = wire.PackageReader()
        pending: list[tuple[int, bytes]] = []

        def reply(kind: int, payload: bytes = b"") -> bytes:
            s.sendall(wire.encode(kind, payload))
            while True:
                pending.extend(reader.feed(s.recv(65536)))
                for i, (k, p) in enumerate(pending):
                    if k == kind:
                        del pending[i]
                        return p

        assert reply(wire.REQUEST_PROTOCOL_VERSION, struct.pack(">H", 2)) == b"\x01"
        setup = reply(wire.CONTROL_PACKAGE_SETUP_OUTPUTS,
                      struct.pack(">d", 500.0) + b"timestamp,actual_q")
        assert setup == b"\x01DOUBLE,VECTOR6D"
        assert reply(wire.CONTROL_PACKAGE_START) == b"\x01"
        stamps: list[float] = []
        end = time.monotonic() + 2.0
        while time.monotonic() < end:
            pending.extend(reader.feed(s.recv(65536)))
            stamps += [struct.unpack(">Bd6d", p)[1] for k, p in pending
                       if k == wire.DATA_PACKAGE]
            pending.clear()
    assert len(stamps) > 500
    assert np.allclose(np.diff(stamps), 0.002, atol=1e-9)


@pytest.mark.parametrize("speed_mm_s", [100.0, 250.0])
def test_realtime_servol_line_under_load(ctl: ControllerProcess, rtde: tuple,
                                         speed_mm_s: float, loaded_host: None) -> None:
    c, r = rtde
    start = np.array(r.getActualTCPPose())
    dt, n = 0.002, int(0.15 / (speed_mm_s / 1000.0) / 0.002)
    off_line = 0.0
    target = start.copy()
    for i in range(1, n + 1):
        t_start = c.initPeriod()
        target = start.copy()
        target[0] += 0.15 * i / n
        c.servoL(target.tolist(), 0.5, 0.5, dt, 0.1, 300)
        actual = np.array(r.getActualTCPPose())
        off_line = max(off_line, float(np.hypot(actual[1] - start[1], actual[2] - start[2])))
        c.waitPeriod(t_start)
    time.sleep(0.3)  # the last target is held while the program re-issues it
    c.servoStop()
    no_stop(ctl)
    assert off_line < 0.002
    assert np.allclose(truth_pose(ctl)[:3], target[:3], atol=5e-4)


def test_unsupported_command_is_refused_and_the_program_keeps_running(
        ctl: ControllerProcess, rtde: tuple) -> None:
    c, r = rtde
    t0 = time.monotonic()
    c.forceMode([0.0] * 6, [0, 0, 1, 0, 0, 0], [0.0, 0.0, -10.0, 0.0, 0.0, 0.0], 2,
                [2.0, 2.0, 1.5, 1.0, 1.0, 1.0])
    assert wait_until(lambda: any("forceMode is not simulated" in m
                                  for m in ctl.state()["messages"]), 2.0)
    assert time.monotonic() - t0 < 3.0
    with contextlib.suppress(AssertionError):
        wait_until(lambda: not c.isProgramRunning(), 1.0)  # the client may see the short stop
    assert wait_until(c.isProgramRunning, 3.0)
    q = r.getActualQ()
    target = list(q)
    target[5] += 0.1
    assert c.moveJ(target, 1.0, 1.0)
    assert np.allclose(truth_q(ctl), target, atol=1e-4)
    assert c.isJointsWithinSafetyLimits(target)
    assert not c.isJointsWithinSafetyLimits([7.0, *target[1:]])
    assert c.getJointTorques() == [0.0] * 6


def test_move_until_contact_stops_on_the_contact_surface(ctl: ControllerProcess,
                                                         rtde: tuple) -> None:
    c, r = rtde
    z0 = r.getActualTCPPose()[2]
    ctl.set_contact_plane_z(z0 - 0.04)  # a table 40 mm below the tool
    t0 = time.monotonic()
    assert c.moveUntilContact([0.0, 0.0, -0.05, 0.0, 0.0, 0.0], [0.0] * 6, 0.5)
    assert 0.5 < time.monotonic() - t0 < 10.0  # 40 mm at 50 mm/s, then back to the contact
    assert truth_pose(ctl)[2] == pytest.approx(z0 - 0.04, abs=1e-4)
    no_stop(ctl)


def test_custom_script_function_runs_the_supported_subset(ctl: ControllerProcess,
                                                          rtde: tuple) -> None:
    c, r = rtde
    script = ("movej([0.2, -1.571, 1.571, -1.571, -1.571, 0.0], a=1.0, v=0.5)\n"
              "set_standard_digital_out(2, True)")
    t0 = time.monotonic()
    assert c.sendCustomScriptFunction("custom", script)
    assert time.monotonic() - t0 < 20.0
    assert np.allclose(truth_q(ctl), [0.2, -1.571, 1.571, -1.571, -1.571, 0.0], atol=1e-4)
    assert wait_until(lambda: r.getDigitalOutState(2), 2.0)
    assert wait_until(c.isProgramRunning, 5.0)  # ur_rtde's own script is back
    assert c.moveJ(HOME_Q, 1.0, 1.0)


def test_protective_stop_unlock_power_and_restart(ctl: ControllerProcess) -> None:
    db = dashboard_client.DashboardClient(ctl.host)
    db.connect()
    r = rtde_receive.RTDEReceiveInterface(ctl.host)
    try:
        ctl.protective_stop()
        assert wait_until(lambda: r.isProtectiveStopped(), 2.0)
        t_stop = time.monotonic()
        with pytest.raises(RuntimeError, match="Cannot unlock protective stop until 5s"):
            db.unlockProtectiveStop()  # refused within 5 s, as on a real controller
        assert r.isProtectiveStopped()
        assert wait_until(lambda: time.monotonic() - t_stop > 5.2, 7.0)
        db.unlockProtectiveStop()
        assert wait_until(lambda: not r.isProtectiveStopped(), 2.0)
        db.powerOff()
        assert wait_until(lambda: r.getRobotMode() == 3, 2.0)
        db.powerOn()
        db.brakeRelease()
        assert wait_until(lambda: r.getRobotMode() == 7, 5.0)
        host = ctl.host
        ctl.kill()  # the controller dies; a fresh one comes up on the same address
        with ControllerProcess(host, powered=True) as again:
            assert wait_until(lambda: again.state()["robot_mode"] == "RUNNING", 10.0)
            assert wait_until(lambda: r.reconnect(), 10.0, poll_s=0.5)
            assert wait_until(lambda: r.getRobotMode() == 7, 5.0)
            c = rtde_control.RTDEControlInterface(host)
            q = list(r.getActualQ())
            q[0] += 0.05
            assert c.moveJ(q)
            assert np.allclose(again.state()["q"], q, atol=1e-4)
            c.stopScript()
            c.disconnect()
    finally:
        r.disconnect()
        db.disconnect()


def test_dashboard_program_list(ctl: ControllerProcess) -> None:
    db = dashboard_client.DashboardClient(ctl.host)
    db.connect()
    try:
        with pytest.raises(RuntimeError):
            db.loadURP("missing.urp")
        db.loadURP("wiggle.urp")
        assert "wiggle.urp" in db.getLoadedProgram()
        db.play()
        assert wait_until(lambda: "PLAYING" in db.programState(), 2.0)
        assert wait_until(lambda: ctl.state()["moving"], 2.0)
        db.pause()
        assert wait_until(lambda: "PAUSED" in db.programState(), 2.0)
        assert wait_until(lambda: not ctl.state()["moving"], 3.0)
        db.play()
        assert wait_until(lambda: "STOPPED" in db.programState(), 15.0)
        assert np.allclose(truth_q(ctl), HOME_Q, atol=1e-4)
    finally:
        db.disconnect()


# -- python-urx: secondary interface and URScript ------------------------------------------

def test_urx_reads_the_pose_and_sends_a_movel(ctl: ControllerProcess) -> None:
    urx = pytest.importorskip("urx")
    rob = urx.URRobot(ctl.host)
    try:
        pose = rob.getl()
        assert np.allclose(pose, truth_pose(ctl), atol=1e-6)
        assert np.allclose(rob.getj(), truth_q(ctl), atol=1e-6)
        target = list(pose)
        target[2] -= 0.05
        # wait=False: urx 0.11 reads e-Series RobotModeData (47 bytes) with its pre-3.0 layout
        # and so never sees the robot "running"; it polls the pose like its own wait does
        rob.movel(target, acc=0.5, vel=0.1, wait=False)
        assert wait_until(lambda: np.allclose(rob.getl(), target, atol=1e-5)
                          and not rob.is_program_running(), 10.0, poll_s=0.05)
        assert np.allclose(truth_pose(ctl), target, atol=1e-5)
        # urx's set_digital_out sends the pre-3.0 form "digital_out[3]=True", which the
        # simulator (like a 5.x controller's compiler) refuses with a message
        rob.set_digital_out(3, True)
        assert wait_until(lambda: any("Compile error" in m for m in ctl.state()["messages"]),
                          3.0)
        rob.send_program("set_standard_digital_out(3, True)")
        r = rtde_receive.RTDEReceiveInterface(ctl.host)
        assert wait_until(lambda: r.getDigitalOutState(3), 3.0)
        r.disconnect()
    finally:
        rob.close()


def test_urx_set_tcp_during_its_movej_replaces_the_program(ctl: ControllerProcess) -> None:
    """urx's set_tcp sends a one-line program; on a controller a new main program replaces
    the running one: the movej stops, then the TCP is set (no runtime error)."""
    urx = pytest.importorskip("urx")
    rob = urx.URRobot(ctl.host)
    try:
        q = list(rob.getj())
        target = list(q)
        target[0] += 0.8
        rob.movej(target, acc=0.5, vel=0.3, wait=False)
        assert wait_until(lambda: abs(truth_q(ctl)[0] - q[0]) > 0.02, 5.0)
        rob.set_tcp((0.0, 0.0, 0.1, 0.0, 0.0, 0.0))
        assert wait_until(lambda: np.allclose(ctl.state()["tcp_offset"],
                                              [0, 0, 0.1, 0, 0, 0]), 5.0)
        stopped_at = truth_q(ctl)[0]
        assert abs(stopped_at - target[0]) > 0.3  # the move did not go on to its target
        time.sleep(0.3)
        assert truth_q(ctl)[0] == pytest.approx(stopped_at, abs=1e-9)
        assert not any("Runtime error" in m for m in ctl.state()["messages"])
        no_stop(ctl)
    finally:
        rob.close()


def test_realtime_port_streams_the_1116_byte_package(ctl: ControllerProcess) -> None:
    with socket.create_connection((ctl.host, 30003), timeout=3.0) as s:
        buf = b""
        while len(buf) < 3 * 1116:
            buf += s.recv(65536)
        stamps = []
        for k in range(3):
            size = struct.unpack_from(">i", buf, k * 1116)[0]
            assert size == 1116
            values = struct.unpack_from(">139d", buf, k * 1116 + 4)
            stamps.append(values[0])
            q_actual = values[31:37]
            assert np.allclose(q_actual, truth_q(ctl), atol=1e-6)
            assert values[94] == 7.0  # robot mode RUNNING
        assert np.allclose(np.diff(stamps), 0.002, atol=1e-9)
        # a URScript line on the same port is executed
        s.sendall(b"movej([0.1, -1.571, 1.571, -1.571, -1.571, 0.0], a=1.0, v=0.5)\n")
        assert wait_until(lambda: np.allclose(truth_q(ctl)[0], 0.1, atol=1e-4), 10.0)


def test_secondary_state_message_layout(ctl: ControllerProcess) -> None:
    with socket.create_connection((ctl.host, 30002), timeout=3.0) as s:
        buf = b""
        while len(buf) < 5 or len(buf) < struct.unpack_from(">i", buf)[0]:
            buf += s.recv(65536)
        size, kind = struct.unpack_from(">iB", buf, 0)
        assert kind == 20, kind  # the version message comes first
        assert buf[5 + 8 + 2] == len(b"URControl")
        buf = buf[size:]
        while len(buf) < 5 or len(buf) < struct.unpack_from(">i", buf)[0]:
            buf += s.recv(65536)
        size, kind = struct.unpack_from(">iB", buf, 0)
        assert kind == 16
        sizes: dict[int, int] = {}
        off = 5
        while off < size:
            sub_size, sub_type = struct.unpack_from(">iB", buf, off)
            sizes[sub_type] = sub_size
            if sub_type == 4:
                pose = struct.unpack_from(">6d", buf, off + 5)
                assert np.allclose(pose, truth_pose(ctl), atol=1e-6)
            off += sub_size
        assert sizes == {0: 47, 1: 251, 2: 37, 3: 74, 4: 101, 5: 225, 7: 61, 8: 9}


# -- pyrobotiqgripper -----------------------------------------------------------------------

def test_pyrobotiqgripper_default_calls() -> None:
    rq = pytest.importorskip("pyrobotiqgripper")
    with FakeGripper(activation_time_s=0.3) as fake:
        g = rq.RobotiqGripper(com_port=fake.port)
        g.connect()
        try:
            g.activate()
            assert fake.model.status_bytes()[0] & 0x31 == 0x31
            g.close()
            assert fake.model.status_bytes()[4] == 255
            g.open()
            assert fake.model.status_bytes()[4] == 0
            g.move(100)
            assert g.position() == 100
            g.calibrate_mm(closemm=0, openmm=85)
            g.move_mm(40)
            assert math.isclose(g.position_mm(), 40.0, abs_tol=0.5)
            g.stop()
            assert fake.model.status_bytes()[0] & 0x08 == 0  # rGTO cleared: stopped
        finally:
            g.disconnect()
