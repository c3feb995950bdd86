"""The simulated UR controller on the wire: RTDE bytes, dashboard texts, and the unmodified
ur_rtde client (control, receive, IO, dashboard) driving it.

The controller runs in a child process: ur_rtde's constructors hold the GIL while they talk
to the controller, so client and controller cannot share one Python process.
"""

from __future__ import annotations

import math
import socket
import struct
import time
from collections.abc import Iterator

import dashboard_client
import numpy as np
import pytest
import rtde_control
import rtde_io
import rtde_receive
import script_client

from estimator.transforms import T_from_ur_pose
from fakes.ur_controller import rtde
from fakes.ur_controller.process import ControllerProcess
from fakes.ur_controller.script import parse_program
from fakes.ur_controller.urscript import split_programs
from tests.support.waiting import wait_until

# The ur_rtde clients run in this process and block inside C++ (movePath waits for the program
# without a deadline): a signal cannot interrupt them, a watchdog thread can end the run.
pytestmark = pytest.mark.timeout(60, method="thread")


def profile_time(distance: float, v: float, a: float) -> float:
    """Duration of a trapezoidal (or triangular) profile from rest to rest."""
    if distance >= v * v / a:
        return distance / v + v / a
    return 2.0 * math.sqrt(distance / a)


def assert_about(measured_s: float, expected_s: float) -> None:
    """Loaded CI machines: +-30 % and 0.3 s of slack."""
    assert expected_s * 0.7 - 0.3 <= measured_s <= expected_s * 1.3 + 0.3, (
        f"took {measured_s:.3f} s, profile says {expected_s:.3f} s")


# -- codec, no network -----------------------------------------------------------------------

def test_package_reader_splits_and_joins_packages() -> None:
    data = rtde.encode(rtde.CONTROL_PACKAGE_START, b"\x01") + rtde.encode_text("hi")
    reader = rtde.PackageReader()
    assert reader.feed(data[:2]) == []
    out = reader.feed(data[2:])
    assert out[0] == (rtde.CONTROL_PACKAGE_START, b"\x01")
    assert out[1][0] == rtde.TEXT_MESSAGE
    assert out[1][1] == b"\x02hi\x09URControl\x03"
    assert data[:3] == b"\x00\x04\x53"  # uint16 size incl. header, uint8 type, big-endian


def test_variable_types_match_the_rtde_guide() -> None:
    assert rtde.output_variable("actual_TCP_pose")[0] == "VECTOR6D"  # type: ignore[index]
    assert rtde.output_variable("runtime_state")[0] == "UINT32"  # type: ignore[index]
    assert rtde.output_variable("joint_mode")[0] == "VECTOR6INT32"  # type: ignore[index]
    assert rtde.output_variable("output_int_register_47")[0] == "INT32"  # type: ignore[index]
    assert rtde.output_variable("output_int_register_48") is None
    assert rtde.output_variable("no_such_variable") is None
    assert rtde.input_variable("input_double_register_5")[0] == "DOUBLE"  # type: ignore[index]
    assert rtde.input_variable("standard_digital_output_mask")[0] == "UINT8"  # type: ignore[index]
    assert rtde.input_variable("actual_q") is None  # outputs cannot be written


def _control_program(path_code: str = "") -> str:
    """ur_rtde's own control script as its client uploads it (injections applied)."""
    text = script_client.ScriptClient("127.0.0.1", 5, 11).getScript()
    text = text.replace("# float register offset\n", "# float register offset\n24", 1)
    text = text.replace("# int register offset\n", "# int register offset\n24", 1)
    text = text.replace("# inject move path\n", "# inject move path\n" + path_code, 1)
    return "def rtde_control():\n" + text + "end\n"


def test_the_real_control_script_is_recognised_with_its_injections() -> None:
    path = ("\tsignal_async_progress(0)\n\tmovel(p[0.1,0.2,0.3,0,3.14,0],a=1.2,v=0.25,r=0)\n"
            "\tsignal_async_progress(1)\n\tmovej([0,-1.5,1.5,-1.5,-1.5,0],a=1.4,v=1.05,r=0.01)\n")
    programs, rest = split_programs(_control_program(path) + "def part")
    assert len(programs) == 1 and rest == "def part"
    prog = parse_program(programs[0])
    assert prog is not None
    assert (prog.int_offset, prog.float_offset) == (24, 24)
    assert prog.path == [("movel", [0.1, 0.2, 0.3, 0.0, 3.14, 0.0], 0.25, 1.2, 0.0),
                         ("movej", [0.0, -1.5, 1.5, -1.5, -1.5, 0.0], 1.05, 1.4, 0.01)]
    assert parse_program("def other():\n  textmsg(1)\nend\n") is None


# -- one controller per test ----------------------------------------------------------------------

@pytest.fixture
def ctl() -> Iterator[ControllerProcess]:
    with ControllerProcess(powered=True) as proc:
        deadline = time.monotonic() + 5.0
        while proc.state()["robot_mode"] != "RUNNING" and time.monotonic() < deadline:
            time.sleep(0.05)
        yield proc


class RawRTDE:
    """A minimal RTDE client on a plain socket, to check bytes the library hides."""

    def __init__(self, host: str) -> None:
        self.sock = socket.create_connection((host, rtde.RTDE_PORT), timeout=3.0)
        self.reader = rtde.PackageReader()
        self.pending: list[tuple[int, bytes]] = []

    def next(self, wanted: int | None = None) -> tuple[int, bytes]:
        while True:
            while self.pending:
                msg = self.pending.pop(0)
                if wanted is None or msg[0] == wanted:
                    return msg
            self.pending.extend(self.reader.feed(self.sock.recv(65536)))

    def request(self, msg_type: int, payload: bytes = b"") -> bytes:
        self.sock.sendall(rtde.encode(msg_type, payload))
        return self.next(msg_type)[1]

    def close(self) -> None:
        self.sock.close()


def test_rtde_setup_replies_and_data_package_widths(ctl: ControllerProcess) -> None:
    c = RawRTDE(ctl.host)
    try:
        assert c.request(rtde.REQUEST_PROTOCOL_VERSION, struct.pack(">H", 2)) == b"\x01"
        version = struct.unpack(">IIII", c.request(rtde.GET_URCONTROL_VERSION))
        assert version[:2] >= (5, 11)
        reply = c.request(rtde.CONTROL_PACKAGE_SETUP_OUTPUTS,
                          struct.pack(">d", 125.0) + b"timestamp,bogus_name,")
        assert reply == b"\x00DOUBLE,NOT_FOUND"
        names = b"timestamp,actual_q,robot_mode,runtime_state,joint_mode,actual_digital_output_bits"
        reply = c.request(rtde.CONTROL_PACKAGE_SETUP_OUTPUTS, struct.pack(">d", 125.0) + names)
        assert reply == b"\x01DOUBLE,VECTOR6D,INT32,UINT32,VECTOR6INT32,UINT64"
        assert c.request(rtde.CONTROL_PACKAGE_START) == b"\x01"
        _, first = c.next(rtde.DATA_PACKAGE)
        fmt = struct.Struct(">B d 6d i I 6i Q")
        assert len(first) == fmt.size
        fields = fmt.unpack(first)
        q_sim = ctl.state()["q"]
        assert np.allclose(fields[2:8], q_sim, atol=1e-6)
        assert fields[8] == 7 and fields[9] == 1  # RUNNING; program STOPPED
        t0 = time.monotonic()
        stamps = [fields[1]]
        while time.monotonic() - t0 < 1.0:
            stamps.append(fmt.unpack(c.next(rtde.DATA_PACKAGE)[1])[1])
        rate = (len(stamps) - 1) / (stamps[-1] - stamps[0])
        assert 125 * 0.7 < rate < 125 * 1.3, f"streamed at {rate:.0f} Hz, asked for 125"
        assert c.request(rtde.CONTROL_PACKAGE_PAUSE) == b"\x01"
    finally:
        c.close()


def test_input_registers_in_use_by_another_connection(ctl: ControllerProcess) -> None:
    a, b = RawRTDE(ctl.host), RawRTDE(ctl.host)
    try:
        assert a.request(rtde.CONTROL_PACKAGE_SETUP_INPUTS,
                         b"input_int_register_0,input_double_register_0") == b"\x01INT32,DOUBLE"
        assert a.request(rtde.CONTROL_PACKAGE_SETUP_INPUTS,
                         b"input_int_register_0") == b"\x02INT32"  # ids count per connection
        assert b.request(rtde.CONTROL_PACKAGE_SETUP_INPUTS,
                         b"input_int_register_0,input_int_register_1") == b"\x00IN_USE,INT32"
        assert b.request(rtde.CONTROL_PACKAGE_SETUP_INPUTS,
                         b"input_int_register_1") == b"\x01INT32"
    finally:
        a.close()
    time.sleep(0.3)  # the closed connection's registers are released
    try:
        assert b.request(rtde.CONTROL_PACKAGE_SETUP_INPUTS,
                         b"input_int_register_0") == b"\x02INT32"
    finally:
        b.close()


def test_dashboard_texts(ctl: ControllerProcess) -> None:
    db = dashboard_client.DashboardClient(ctl.host)
    db.connect()
    try:
        assert db.polyscopeVersion().startswith("5.11")
        assert db.robotmode() == "Robotmode: RUNNING"
        assert db.safetystatus() == "Safetystatus: NORMAL"
        assert db.isInRemoteControl()
        assert db.getSerialNumber().isdigit()
        assert db.programState().startswith("STOPPED")
        db.unlockProtectiveStop()  # nothing to unlock: accepted
        ctl.protective_stop()
        time.sleep(0.1)
        assert db.safetystatus() == "Safetystatus: PROTECTIVE_STOP"
        with pytest.raises(RuntimeError, match="Cannot unlock protective stop until 5s"):
            db.unlockProtectiveStop()
        db.send("make coffee\n")
        assert db.receive() == "could not understand: 'make coffee'"
        db.powerOff()
        time.sleep(0.1)
        assert db.robotmode() == "Robotmode: POWER_OFF"
    finally:
        db.disconnect()


@pytest.fixture
def clients(ctl: ControllerProcess) -> Iterator[tuple[rtde_control.RTDEControlInterface,
                                                        rtde_receive.RTDEReceiveInterface]]:
    r = rtde_receive.RTDEReceiveInterface(ctl.host)
    c = rtde_control.RTDEControlInterface(ctl.host)
    yield c, r
    c.stopScript()
    c.disconnect()
    r.disconnect()


def test_control_script_runs_and_moves_arrive_in_profile_time(
        ctl: ControllerProcess, clients: tuple) -> None:
    c, r = clients
    assert c.isProgramRunning() and r.getRuntimeState() == 2
    start = r.getActualTCPPose()
    target = list(start)
    target[0] += 0.08
    target[2] -= 0.12
    t0 = time.monotonic()
    assert c.moveL(target, 0.2, 1.0)
    assert_about(time.monotonic() - t0, profile_time(math.dist(start[:3], target[:3]), 0.2, 1.0))
    assert np.allclose(ctl.state()["tcp_pose"], target, atol=1e-6)
    assert np.allclose(r.getActualTCPPose(), target, atol=1e-6)

    q = r.getActualQ()
    q_target = list(q)
    q_target[0] += 0.4
    q_target[5] -= 0.3
    t0 = time.monotonic()
    assert c.moveJ(q_target, 1.0, 2.0)
    assert_about(time.monotonic() - t0, profile_time(0.4, 1.0, 2.0))
    assert np.allclose(ctl.state()["q"], q_target, atol=1e-6)

    fk = c.getForwardKinematics()
    assert np.allclose(fk, r.getActualTCPPose(), atol=1e-6)
    assert np.allclose(c.getInverseKinematics(fk), q_target, atol=1e-5)


def test_async_path_reports_progress(ctl: ControllerProcess, clients: tuple) -> None:
    c, r = clients
    p0 = r.getActualTCPPose()
    waypoints = []
    for dz in (-0.05, -0.10, -0.05):
        wp = list(p0)
        wp[2] += dz
        waypoints.append([*wp, 0.25, 1.2, 0.0])
    assert c.moveL(waypoints, True)  # async
    seen = []
    t0 = time.monotonic()
    while time.monotonic() - t0 < 5.0:
        status = c.getAsyncOperationProgressEx()
        if not status.isAsyncOperationRunning():
            break
        if not seen or seen[-1] != status.progress():
            seen.append(status.progress())
        time.sleep(0.005)
    assert seen == [0, 1, 2]
    assert c.getAsyncOperationProgress() < 0  # finished
    assert wait_until(lambda: np.allclose(r.getActualTCPPose(), waypoints[-1][:6], atol=1e-6)), \
        (r.getActualTCPPose(), waypoints[-1][:6])


def test_speed_servo_and_stops(ctl: ControllerProcess, clients: tuple) -> None:
    c, r = clients
    p0 = r.getActualTCPPose()
    t0 = time.monotonic()
    assert c.speedL([0.05, 0.0, 0.0, 0.0, 0.0, 0.0], 0.5, 0.0)
    # at speed after the 0.1 s ramp (later only when the loaded host delays the stream)
    assert wait_until(lambda: r.getActualTCPSpeed()[0] == pytest.approx(0.05, abs=1e-3)), \
        r.getActualTCPSpeed()
    t_at_speed = time.monotonic()
    time.sleep(0.5)  # speedL keeps going, as the real control script's speed thread does
    assert r.getActualTCPSpeed()[0] == pytest.approx(0.05, abs=1e-3)
    t1 = time.monotonic()
    assert c.speedStop(1.0)
    t2 = time.monotonic()
    assert wait_until(lambda: abs(r.getActualTCPSpeed()[0]) < 1e-3), r.getActualTCPSpeed()
    moved = r.getActualTCPPose()[0] - p0[0]
    # 50 mm/s at least from when the stream showed full speed to the stop command, and at most
    # from the speedL command to the stop's return, plus the braking
    assert 0.05 * (t1 - t_at_speed) - 0.005 < moved < 0.05 * (t2 - t0) + 0.005

    q = r.getActualQ()
    for i in range(100):  # 0.05 rad on joint 0 in 0.2 s, streamed at 500 Hz
        target = list(q)
        target[0] += 0.0005 * (i + 1)
        t = c.initPeriod()
        c.servoJ(target, 0.0, 0.0, 0.008, 0.1, 300)
        c.waitPeriod(t)
    assert wait_until(lambda: r.getActualQ()[0] == pytest.approx(q[0] + 0.05, abs=5e-3)), \
        (r.getActualQ()[0], q[0] + 0.05)
    assert c.servoStop(2.0)

    start = r.getActualTCPPose()
    far = list(start)
    far[2] -= 0.2
    assert c.moveL(far, 0.1, 0.5, True)
    time.sleep(0.5)
    c.stopL(2.0)  # returns nothing
    assert wait_until(lambda: max(map(abs, r.getActualTCPSpeed())) < 1e-6), r.getActualTCPSpeed()
    stopped_at = r.getActualTCPPose()[2]
    time.sleep(0.3)
    assert r.getActualTCPPose()[2] == pytest.approx(stopped_at, abs=1e-6)
    assert start[2] - 0.15 < stopped_at < start[2] - 0.01


def test_second_control_connection_is_rejected(ctl: ControllerProcess, clients: tuple) -> None:
    with pytest.raises(RuntimeError, match="already in use"):
        rtde_control.RTDEControlInterface(ctl.host)
    c, _ = clients
    assert c.isProgramRunning()  # the first client is unaffected


def test_not_in_remote_control_is_refused(ctl: ControllerProcess) -> None:
    ctl.set_remote_control(False)
    with pytest.raises(RuntimeError, match="enable remote control"):
        rtde_control.RTDEControlInterface(ctl.host)


def test_unpowered_controller_says_why_the_control_script_did_not_start() -> None:
    """The standalone controller starts powered off: ur_rtde only reports "Failed to start
    control script"; the reason goes to every streaming RTDE client as an error-level text
    message (protocol 2: message, source, warning level)."""
    with ControllerProcess() as unpowered:
        c = RawRTDE(unpowered.host)
        try:
            assert c.request(rtde.REQUEST_PROTOCOL_VERSION, struct.pack(">H", 2)) == b"\x01"
            c.request(rtde.CONTROL_PACKAGE_SETUP_OUTPUTS, struct.pack(">d", 10.0) + b"timestamp")
            assert c.request(rtde.CONTROL_PACKAGE_START) == b"\x01"
            with pytest.raises(RuntimeError, match="Failed to start control script"):
                rtde_control.RTDEControlInterface(unpowered.host)
            _, payload = c.next(rtde.TEXT_MESSAGE)
            n = payload[0]
            message = payload[1:1 + n].decode()
            source = payload[2 + n:2 + n + payload[1 + n]].decode()
            level = payload[-1]
            assert source == "URControl" and level == rtde.LEVEL_ERROR
            assert "POWER_OFF" in message and "power on" in message, message
        finally:
            c.close()


def test_io_interface_and_protective_stop_program_state(
        ctl: ControllerProcess, clients: tuple) -> None:
    c, r = clients
    io = rtde_io.RTDEIOInterface(ctl.host)
    try:
        assert io.setStandardDigitalOut(3, True)
        assert io.setSpeedSlider(0.5)
        time.sleep(0.1)
        assert r.getActualDigitalOutputBits() == 1 << 3
        assert r.getTargetSpeedFraction() == pytest.approx(0.5)
    finally:
        io.disconnect()
    assert c.triggerProtectiveStop() is False  # the client returns False on a safety stop
    time.sleep(0.1)
    assert r.isProtectiveStopped()
    assert r.getRuntimeState() == 1  # the control program stopped with the stop
    p0 = r.getActualTCPPose()
    target = list(p0)
    target[2] -= 0.05
    assert c.moveL(target, 0.1, 0.5) is False
    assert np.allclose(r.getActualTCPPose(), p0, atol=1e-9)


def test_rtde_watchdog_stops_the_program_and_unsimulated_commands_are_refused(
        ctl: ControllerProcess, clients: tuple) -> None:
    c, r = clients
    # 2 Hz: the client must write within 500 ms (a faster rate would also end the program
    # whenever this test's own process is not scheduled for that long on a loaded host)
    assert c.setWatchdog(2.0)
    for _ in range(20):
        assert c.kickWatchdog()
        time.sleep(0.01)
    assert r.getRuntimeState() == 2
    t_kick = time.monotonic()
    deadline = t_kick + 3.0  # no kicks: the controller stops the program
    while r.getRuntimeState() != 1 and time.monotonic() < deadline:
        time.sleep(0.01)
    assert r.getRuntimeState() == 1
    assert time.monotonic() - t_kick > 0.4  # not before the watchdog's time
    messages = ctl.state()["messages"]
    assert any("watchdog" in m for m in messages), messages
    assert c.reuploadScript()  # sends the script; returns before it runs
    # ur_rtde's control client refuses a command at once while its own RTDE stream (another
    # connection than the receive client's, which a loaded host may read later) does not yet
    # show the script running: wait for both views, as a client of a real controller must
    deadline = time.monotonic() + 3.0
    while ((r.getRuntimeState() != 2 or not c.isProgramRunning())
           and time.monotonic() < deadline):
        time.sleep(0.01)
    assert r.getRuntimeState() == 2 and c.isProgramRunning()
    assert c.teachMode() and c.endTeachMode()  # simulated: nobody pushes the arm
    t0 = time.monotonic()
    # not simulated: refused at once with a message, not a silent success, not a hang
    assert c.moveUntilContact([0.0, 0.0, -0.05, 0.0, 0.0, 0.0]) is False
    assert time.monotonic() - t0 < 2.0
    messages = ctl.state()["messages"]
    assert any(m.startswith("Refused: moveUntilContact") for m in messages), messages
    deadline = time.monotonic() + 3.0  # ... and the program resumes by itself
    while not c.isProgramRunning() and time.monotonic() < deadline:
        time.sleep(0.01)
    q = r.getActualQ()
    target = list(q)
    target[0] += 0.05
    assert c.moveJ(target, 1.0, 1.0)
    deadline = time.monotonic() + 1.0  # the receive client's stream may lag the control's
    while not np.allclose(r.getActualQ(), target, atol=1e-4) and time.monotonic() < deadline:
        time.sleep(0.01)
    assert np.allclose(r.getActualQ(), target, atol=1e-4)


def test_jog_start_and_stop_in_tool_frame(ctl: ControllerProcess, clients: tuple) -> None:
    c, r = clients
    p0 = np.array(r.getActualTCPPose())
    t0 = time.monotonic()
    assert c.jogStart([0.0, 0.0, 0.02, 0.0, 0.0, 0.0],
                      rtde_control.RTDEControlInterface.Feature.FEATURE_TOOL, 0.5)
    time.sleep(0.6)
    t1 = time.monotonic()
    assert c.jogStop()
    t2 = time.monotonic()
    # the receive client is another connection: its next packages (2 ms apart) show the stop
    deadline = t2 + 0.1
    while np.linalg.norm(r.getActualTCPSpeed()[:3]) >= 1e-3 and time.monotonic() < deadline:
        time.sleep(0.002)
    assert np.linalg.norm(r.getActualTCPSpeed()[:3]) < 1e-3
    p1 = np.array(r.getActualTCPPose())
    tool_z = T_from_ur_pose(p0)[:3, 2]
    moved_mm = 1000.0 * (p1[:3] - p0[:3])
    along = float(moved_mm @ tool_z)
    assert 20.0 * (t1 - t0) - 3.0 < along < 20.0 * (t2 - t0) + 1.0, f"jogged {along:.1f} mm"
    assert np.linalg.norm(moved_mm - along * tool_z) < 0.5


# The output names (and types) of UR's RTDE client library's full record configuration
# (record_configuration_v3.xml), as published; the registers are generated below.
RECORD_OUTPUTS = {
    "timestamp": "DOUBLE", "target_q": "VECTOR6D", "target_qd": "VECTOR6D",
    "target_qdd": "VECTOR6D", "target_current": "VECTOR6D", "target_moment": "VECTOR6D",
    "actual_q": "VECTOR6D", "actual_qd": "VECTOR6D", "actual_current": "VECTOR6D",
    "joint_control_output": "VECTOR6D", "actual_TCP_pose": "VECTOR6D",
    "actual_TCP_speed": "VECTOR6D", "actual_TCP_force": "VECTOR6D", "target_TCP_pose": "VECTOR6D",
    "target_TCP_speed": "VECTOR6D", "actual_digital_input_bits": "UINT64",
    "joint_temperatures": "VECTOR6D", "actual_execution_time": "DOUBLE", "robot_mode": "INT32",
    "joint_mode": "VECTOR6INT32", "safety_status": "INT32", "actual_tool_accelerometer": "VECTOR3D",
    "speed_scaling": "DOUBLE", "target_speed_fraction": "DOUBLE", "actual_momentum": "DOUBLE",
    "actual_main_voltage": "DOUBLE", "actual_robot_voltage": "DOUBLE",
    "actual_robot_current": "DOUBLE", "actual_joint_voltage": "VECTOR6D",
    "actual_digital_output_bits": "UINT64", "runtime_state": "UINT32",
    "joint_position_deviation_ratio": "DOUBLE", "payload": "DOUBLE", "payload_cog": "VECTOR3D",
    "payload_inertia": "VECTOR6D", "ft_raw_wrench": "VECTOR6D", "script_control_line": "UINT32",
    "actual_current_window": "VECTOR6D", "elbow_position": "VECTOR3D",
    "elbow_velocity": "VECTOR3D", "robot_status_bits": "UINT32", "safety_status_bits": "UINT32",
    "safety_mode": "INT32", "io_current": "DOUBLE", "tool_mode": "UINT32",
    "tcp_force_scalar": "DOUBLE", "tcp_offset": "VECTOR6D", "dexterity": "DOUBLE",
    "analog_io_types": "UINT32", "standard_analog_input0": "DOUBLE",
    "standard_analog_input1": "DOUBLE", "standard_analog_output0": "DOUBLE",
    "standard_analog_output1": "DOUBLE", "tool_analog_input_types": "UINT32",
    "tool_analog_input0": "DOUBLE", "tool_analog_input1": "DOUBLE",
    "tool_output_voltage": "INT32", "tool_output_voltage_2": "INT32",
    "tool_output_current": "DOUBLE", "tool_output_current_2": "DOUBLE",
    "tool_temperature": "DOUBLE", "tool_output_mode": "UINT8",
    "tool_digital_output0_mode": "UINT8", "tool_digital_output1_mode": "UINT8",
    "euromap67_input_bits": "UINT32", "euromap67_output_bits": "UINT32",
    "euromap67_24V_voltage": "DOUBLE", "euromap67_24V_current": "DOUBLE",
    "actual_configurable_digital_input_bits": "UINT64",
    "actual_configurable_digital_output_bits": "UINT64", "encoder0_raw": "INT32",
    "encoder1_raw": "INT32", "output_bit_registers0_to_31": "UINT32",
    "output_bit_registers32_to_63": "UINT32", "input_bit_registers0_to_31": "UINT32",
    "input_bit_registers32_to_63": "UINT32", "external_force_torque": "VECTOR6D",
    **{f"{d}_bit_register_{i}": "BOOL" for d in ("output", "input") for i in range(64, 128)},
    **{f"{d}_int_register_{i}": "INT32" for d in ("output", "input") for i in range(48)},
    **{f"{d}_double_register_{i}": "DOUBLE" for d in ("output", "input") for i in range(48)},
}


def test_record_configuration_outputs_byte_by_byte(ctl: ControllerProcess) -> None:
    """UR's guide: 'O' carries a double frequency then the comma-separated names;
    the reply is the recipe id then the comma-separated types; 'S' starts, each 'U' carries
    the recipe id and the values at their types' widths, big-endian."""
    names = list(RECORD_OUTPUTS)
    c = RawRTDE(ctl.host)
    try:
        assert c.request(rtde.REQUEST_PROTOCOL_VERSION, struct.pack(">H", 2)) == b"\x01"
        reply = c.request(rtde.CONTROL_PACKAGE_SETUP_OUTPUTS,
                          struct.pack(">d", 125.0) + ",".join(names).encode())
        assert reply[0] == 1
        assert reply[1:].decode().split(",") == [RECORD_OUTPUTS[n] for n in names]
        assert c.request(rtde.CONTROL_PACKAGE_START) == b"\x01"
        fmt = ">B" + "".join(rtde.TYPE_FORMATS[RECORD_OUTPUTS[n]] for n in names)
        first = c.next(rtde.DATA_PACKAGE)[1]
        second = c.next(rtde.DATA_PACKAGE)[1]
        assert len(first) == struct.calcsize(fmt)
        a, b = struct.unpack(fmt, first), struct.unpack(fmt, second)
        assert a[0] == 1 and b[1] - a[1] == pytest.approx(0.008, abs=1e-9)  # 125 Hz
        q = a[1 + 6 * 5 + 1:1 + 6 * 5 + 1 + 6]  # actual_q after timestamp and 5 vectors
        assert np.allclose(q, ctl.state()["q"], atol=1e-9)
    finally:
        c.close()
