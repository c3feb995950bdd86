"""Robotiq gripper adapter: exact bytes on the wire, then end to end against the fake over both
links a cell has (a pseudo-terminal as a USB-RS-485 adapter's device, and a TCP relay as a UR
controller's tool flange gives).

The byte-level half follows the idea of pymeasure's expected_protocol: a scripted serial port
asserts every request the adapter writes and feeds back exact reply bytes. Request frames are
the examples printed in Robotiq's 2F-85 manual (activation, close at full speed and force).
"""

from __future__ import annotations

import socket
import time
from collections.abc import Iterator

import pytest

from drivers.errors import (
    ConnectionLostError,
    DeviceTimeoutError,
    MotionError,
    NotReadyError,
    ProtocolError,
)
from drivers.gripper import Gripper
from drivers.robotiq import RobotiqGripper, mm_to_position, position_to_mm
from fakes.gripper import (
    MANUAL_EXAMPLE_OPEN_LIMIT,
    BenchPiece,
    FakeGripper,
    GripperModel,
    speed_units_per_s,
)
from tests.support.protocol import Script, ScriptedSerial, expected_serial

H = bytes.fromhex

STATUS_REQUEST = H("09 04 07 D0 00 03 B1 CE")
WRITE_REPLY = H("09 10 03 E8 00 03 01 30")
RESET_REQUEST = H("09 10 03 E8 00 03 06 00 00 00 00 00 00 73 30")  # manual: clear rACT
ACTIVATE_REQUEST = H("09 10 03 E8 00 03 06 01 00 00 00 00 00 72 E1")  # manual: set rACT
CLOSE_FULL_REQUEST = H("09 10 03 E8 00 03 06 09 00 00 FF FF FF 42 29")  # manual: close
HALT_REQUEST = H("09 10 03 E8 00 03 06 01 00 00 FF 00 00 42 D1")  # rGTO cleared, rACT kept
HALTED = H("09 04 06 31 00 00 FF 7F 00 13 72")  # gGTO=0, activated, fingers at 0x7F
NOT_ACTIVATED = H("09 04 06 00 00 00 00 00 00 07 53")
ACTIVATING = H("09 04 06 11 00 00 00 00 00 04 12")
ACTIVATED_OPEN = H("09 04 06 31 00 00 00 00 00 03 72")
CLOSING = H("09 04 06 39 00 00 FF 0E 0A B6 6D")
CLOSED_ON_OBJECT = H("09 04 06 B9 00 00 FF BD 00 5C 9A")  # gOBJ=2 at gPO=0xBD
OVERCURRENT = H("09 04 06 39 00 0E FF 40 00 01 22")


@pytest.fixture
def scripted(monkeypatch: pytest.MonkeyPatch) -> Iterator[list[ScriptedSerial]]:
    """Every serial port the adapter opens is the next scripted one (see :func:`make`)."""
    with expected_serial(monkeypatch) as made:
        yield made


def make(made: list[ScriptedSerial], script: Script,
         timeout_s: float = 0.1) -> tuple[RobotiqGripper, ScriptedSerial]:
    port = ScriptedSerial(script)
    made.append(port)
    g = RobotiqGripper("scripted", timeout_s=timeout_s, retries=0, poll_interval_s=0.0)
    return g, port


def test_adapter_is_a_gripper() -> None:
    assert isinstance(RobotiqGripper("/dev/null"), Gripper)


def test_position_mapping_covers_the_stroke() -> None:
    assert position_to_mm(0) == 85.0
    assert position_to_mm(255) == 0.0
    assert mm_to_position(85.0) == 0 and mm_to_position(0.0) == 255
    assert abs(position_to_mm(mm_to_position(40.0)) - 40.0) < 85 / 255


def test_connect_and_status_bytes(scripted: list[ScriptedSerial]) -> None:
    g, port = make(scripted, [(STATUS_REQUEST, NOT_ACTIVATED), (STATUS_REQUEST, CLOSED_ON_OBJECT)])
    g.connect()
    s = g.status()
    assert s.activated and s.object_detected and not s.moving and s.fault is None
    assert s.position_mm == pytest.approx(85.0 * (1 - 0xBD / 255), abs=0.01)
    assert port.written == [STATUS_REQUEST, STATUS_REQUEST]


def test_activation_sequence_matches_manual(scripted: list[ScriptedSerial]) -> None:
    g, _ = make(scripted, [
        (STATUS_REQUEST, NOT_ACTIVATED),  # connect
        (STATUS_REQUEST, NOT_ACTIVATED),  # activate: is it already active?
        (RESET_REQUEST, WRITE_REPLY),
        (ACTIVATE_REQUEST, WRITE_REPLY),
        (STATUS_REQUEST, ACTIVATING),
        (STATUS_REQUEST, ACTIVATED_OPEN),
    ])
    g.connect()
    s = g.activate()
    assert s.activated and s.position_mm == 85.0


def test_close_full_speed_force_waits_for_object(scripted: list[ScriptedSerial]) -> None:
    g, _ = make(scripted, [
        (STATUS_REQUEST, ACTIVATED_OPEN),  # connect
        (STATUS_REQUEST, ACTIVATED_OPEN),  # move: activated?
        (CLOSE_FULL_REQUEST, WRITE_REPLY),
        (STATUS_REQUEST, CLOSING),
        (STATUS_REQUEST, CLOSED_ON_OBJECT),
    ])
    g.connect()
    s = g.move(0.0, speed_pct=100, force_pct=100)
    assert s.object_detected and s.position_mm == pytest.approx(22.0, abs=0.01)


def test_stop_clears_go_to_and_keeps_activation(scripted: list[ScriptedSerial]) -> None:
    """The manual's stop: the action request with rGTO cleared; the wait that follows ends at
    once (gGTO 0: the fingers stay where they are)."""
    g, _ = make(scripted, [
        (STATUS_REQUEST, ACTIVATED_OPEN),  # connect
        (STATUS_REQUEST, ACTIVATED_OPEN),  # move: activated?
        (CLOSE_FULL_REQUEST, WRITE_REPLY),
        (STATUS_REQUEST, CLOSING),  # move(wait=False) reports
        (HALT_REQUEST, WRITE_REPLY),
        (STATUS_REQUEST, HALTED),  # stop reports
        (STATUS_REQUEST, HALTED),  # wait_for_motion: halted, so over
    ])
    g.connect()
    assert g.move(0.0, speed_pct=100, force_pct=100, wait=False).moving
    halted = g.stop()
    assert not halted.moving and halted.position_mm == pytest.approx(position_to_mm(0x7F), abs=0.01)
    assert g.wait_for_motion().position_mm == halted.position_mm


def test_crc_error_is_a_protocol_error(scripted: list[ScriptedSerial]) -> None:
    bad = ACTIVATED_OPEN[:-1] + b"\x00"
    g, _ = make(scripted, [(STATUS_REQUEST, ACTIVATED_OPEN), (STATUS_REQUEST, bad)])
    g.connect()
    with pytest.raises(ProtocolError, match="CRC error"):
        g.status()


def test_garbage_is_a_protocol_error(scripted: list[ScriptedSerial]) -> None:
    g, _ = make(scripted, [(STATUS_REQUEST, ACTIVATED_OPEN), (STATUS_REQUEST, b"\xff\x00hello")])
    g.connect()
    with pytest.raises(ProtocolError, match="garbage"):
        g.status()


def test_silence_is_a_timeout(scripted: list[ScriptedSerial]) -> None:
    g, _ = make(scripted, [(STATUS_REQUEST, None)], timeout_s=0.2)
    t0 = time.monotonic()
    with pytest.raises(DeviceTimeoutError, match="no answer"):
        g.connect()
    assert 0.15 < time.monotonic() - t0 < 2.0


def test_a_late_answer_to_an_earlier_request_is_skipped(scripted: list[ScriptedSerial]) -> None:
    """RTU frames carry no transaction id: the answer to a write that timed out, arriving
    while the next request waits, must not be taken for that request's answer (a status with
    no registers). The request goes out again and its own answer is used."""
    g, port = make(scripted, [(STATUS_REQUEST, ACTIVATED_OPEN), (ACTIVATE_REQUEST, None),
                              (STATUS_REQUEST, WRITE_REPLY + CLOSED_ON_OBJECT),
                              (STATUS_REQUEST, CLOSED_ON_OBJECT)])
    g.connect()
    with pytest.raises(DeviceTimeoutError):
        g.write_action(0x01)
    assert g.status().object_detected
    assert port.written[-2:] == [STATUS_REQUEST, STATUS_REQUEST]


def test_only_late_answers_is_a_protocol_error_naming_the_timeout(
        scripted: list[ScriptedSerial]) -> None:
    g, _ = make(scripted, [(STATUS_REQUEST, ACTIVATED_OPEN)]
                + [(STATUS_REQUEST, WRITE_REPLY)] * 3)
    g.connect()
    with pytest.raises(ProtocolError, match=r"answers to other requests.*timeout_s"):
        g.status()


def test_modbus_exception_reply(scripted: list[ScriptedSerial]) -> None:
    g, _ = make(scripted, [(STATUS_REQUEST, ACTIVATED_OPEN), (STATUS_REQUEST, H("09 84 02 43 03"))])
    g.connect()
    with pytest.raises(ProtocolError, match="exception code 2"):
        g.status()


def test_a_failed_port_is_closed_and_reopened_by_the_next_request(
        scripted: list[ScriptedSerial]) -> None:
    """A port that fails under a request (an adapter pulled, a driver error) is closed, not
    dropped: its descriptor and exclusive lock go, and the next request opens the device again,
    so a link that comes back is used without a restart."""
    g, first = make(scripted, [(STATUS_REQUEST, ACTIVATED_OPEN),
                               (STATUS_REQUEST, OSError(5, "Input/output error"))])
    g.connect()
    with pytest.raises(ConnectionLostError, match="reopens"):
        g.status()
    assert not first.is_open
    second = ScriptedSerial([(STATUS_REQUEST, CLOSED_ON_OBJECT)])
    scripted.append(second)
    assert g.status().object_detected
    assert second.written == [STATUS_REQUEST]


def test_move_refused_before_activation_writes_nothing(scripted: list[ScriptedSerial]) -> None:
    g, port = make(scripted, [(STATUS_REQUEST, NOT_ACTIVATED), (STATUS_REQUEST, NOT_ACTIVATED)])
    g.connect()
    with pytest.raises(NotReadyError, match="activate"):
        g.close()
    assert port.written == [STATUS_REQUEST, STATUS_REQUEST]


@pytest.mark.parametrize("kwargs", [
    {"position_mm": -1.0}, {"position_mm": 90.0}, {"position_mm": 10.0, "speed_pct": 120.0},
    {"position_mm": 10.0, "force_pct": -5.0},
])
def test_bad_input_sends_nothing(scripted: list[ScriptedSerial], kwargs: dict[str, float]) -> None:
    g, port = make(scripted, [(STATUS_REQUEST, ACTIVATED_OPEN)])
    g.connect()
    with pytest.raises(ValueError):
        g.move(**kwargs)
    assert port.written == [STATUS_REQUEST]


def test_device_fault_during_motion(scripted: list[ScriptedSerial]) -> None:
    g, _ = make(scripted, [
        (STATUS_REQUEST, ACTIVATED_OPEN), (STATUS_REQUEST, ACTIVATED_OPEN),
        (CLOSE_FULL_REQUEST, WRITE_REPLY), (STATUS_REQUEST, OVERCURRENT),
    ])
    g.connect()
    with pytest.raises(MotionError, match="overcurrent"):
        g.move(0.0, 100, 100)


# -- the fake's model, without a wire --------------------------------------------------------

class Clock:
    def __init__(self) -> None:
        self.t = 0.0

    def __call__(self) -> float:
        return self.t


def test_model_needs_activation_and_takes_time() -> None:
    clock = Clock()
    m = GripperModel(activation_time_s=1.0, clock=clock)
    m.write_request(0, [0x0800, 0x00FF, 0xFFFF])  # go without rACT
    assert m.status_bytes()[2] == 0x07
    m.write_request(0, [0x0100, 0, 0])
    assert (m.status_bytes()[0] >> 4) & 3 == 1  # activating
    clock.t = 1.01
    assert m.status_bytes()[0] == 0x31  # the manual's example: gACT = 1, gSTA = 3, gOBJ = 0
    assert m.status_bytes()[4] == 0
    m.write_request(0, [0x0900, 0x00FF, 0xFFFF])
    assert m.status_bytes()[2] == 0  # the order fault cleared by a valid request
    full_stroke_s = 255 / speed_units_per_s(255)
    assert full_stroke_s == pytest.approx(85 / 150)
    clock.t += full_stroke_s / 2
    mid = m.status_bytes()
    assert mid[0] >> 6 == 0 and 120 < mid[4] < 135
    clock.t += full_stroke_s
    done = m.status_bytes()
    # closed on nothing: at the closed software limit, "at requested position" (0xF9)
    assert done[0] == 0xF9 and done[3] == 0xFF and done[4] == 255


def test_model_with_the_manual_examples_software_limit() -> None:
    """The manual's opening example: full-open request, fingers at 0x0D, status 0xF9."""
    clock = Clock()
    m = GripperModel(activation_time_s=0.1, clock=clock, limits=(MANUAL_EXAMPLE_OPEN_LIMIT, 255))
    m.write_request(0, [0x0100, 0, 0])
    clock.t = 0.2
    assert m.status_bytes()[0] == 0x31
    m.write_request(0, [0x0900, 0x0000, 0xFFFF])
    clock.t = 2.0
    assert m.status_bytes() == [0xF9, 0x00, 0x00, 0x00, 0x0D, 0x00]


# -- end to end over a real pseudo-terminal and a TCP relay -----------------------------------

@pytest.fixture(params=["pty", "tcp"])
def fake(request: pytest.FixtureRequest) -> Iterator[FakeGripper]:
    with FakeGripper(activation_time_s=0.3, transport=request.param) as f:
        yield f


@pytest.fixture
def gripper(fake: FakeGripper) -> Iterator[RobotiqGripper]:
    g = RobotiqGripper(fake.port, timeout_s=0.3, retries=0)
    g.connect()
    yield g
    g.disconnect()


def test_link_activate_open_close_move(gripper: RobotiqGripper) -> None:
    assert not gripper.status().activated
    t0 = time.monotonic()
    assert gripper.activate().activated
    assert 0.25 < time.monotonic() - t0 < 0.3 + 1.0
    t0 = time.monotonic()
    closed = gripper.close()
    took = time.monotonic() - t0
    assert closed.position_mm == 0.0 and not closed.object_detected and not closed.moving
    assert 0.8 * 85 / 150 < took < 85 / 150 + 1.0
    assert gripper.open().position_mm == 85.0
    slow_t0 = time.monotonic()
    s = gripper.move(65.0, speed_pct=0.0)  # 20 mm at the slowest 20 mm/s: about 1 s
    assert s.position_mm == pytest.approx(65.0, abs=0.34)
    assert 0.8 < time.monotonic() - slow_t0 < 1.0 + 1.0


def test_link_object_stops_the_fingers(fake: FakeGripper, gripper: RobotiqGripper) -> None:
    gripper.activate()
    fake.model.set_grasp(BenchPiece(30.0))
    s = gripper.close()
    assert s.object_detected and s.position_mm == pytest.approx(30.0, abs=0.34)
    opened = gripper.open()
    assert not opened.object_detected and opened.position_mm == 85.0


def test_link_no_wait_reports_motion(gripper: RobotiqGripper) -> None:
    gripper.activate()
    assert gripper.move(0.0, speed_pct=0.0, wait=False).moving
    time.sleep(0.3)
    s = gripper.status()
    assert s.moving and 0 < s.position_mm < 85.0
    gripper.open()


def test_link_stop_halts_the_fingers_where_they_are(gripper: RobotiqGripper) -> None:
    gripper.activate()
    gripper.open()
    assert gripper.move(0.0, speed_pct=0.0, wait=False).moving  # 20 mm/s: 4 s to close
    time.sleep(0.3)
    halted = gripper.stop()
    assert not halted.moving
    t0 = time.monotonic()
    done = gripper.wait_for_motion()
    assert time.monotonic() - t0 < 0.5, "the wait after a stop waited for the old request"
    time.sleep(0.3)
    assert abs(gripper.status().position_mm - done.position_mm) < 0.34
    assert 60.0 < done.position_mm < 85.0
    assert gripper.open().position_mm == 85.0  # and it moves again on the next request


def test_link_line_faults_then_recovery(fake: FakeGripper, gripper: RobotiqGripper) -> None:
    fake.inject_line_fault("bad_crc")
    with pytest.raises(ProtocolError, match="CRC"):
        gripper.status()
    fake.inject_line_fault("garbage")
    with pytest.raises(ProtocolError, match="garbage"):
        gripper.status()
    fake.inject_line_fault("no_answer")
    with pytest.raises(DeviceTimeoutError):
        gripper.status()
    assert gripper.status().fault is None  # the line works again


def test_link_retry_hides_one_lost_answer(fake: FakeGripper) -> None:
    g = RobotiqGripper(fake.port, timeout_s=0.3, retries=1)
    g.connect()
    fake.inject_line_fault("bad_crc")
    assert not g.status().activated
    g.disconnect()


def test_link_a_late_answer_does_not_become_the_next_ones(fake: FakeGripper) -> None:
    """A gripper that answers one request later than the client waits (a busy bus, a loaded
    host) answers the next request only after it: the client skips the stale answer. The
    late answer comes between the write's timeout and the end of the next request's wait."""
    g = RobotiqGripper(fake.port, timeout_s=0.4, retries=0)
    g.connect()
    g.activate()
    fake.inject_line_fault("late")
    with pytest.raises(DeviceTimeoutError):
        g.write_action(0x01)
    for _ in range(3):
        assert g.status().activated
    assert g.close().position_mm == 0.0
    g.disconnect()


def test_link_device_fault_and_reset(fake: FakeGripper, gripper: RobotiqGripper) -> None:
    gripper.activate()
    fake.model.inject_fault(0x0E)
    assert "overcurrent" in str(gripper.status().fault)
    with pytest.raises(MotionError, match="overcurrent"):
        gripper.close()
    assert gripper.activate().fault is None  # a reset + activation clears it


def test_link_wrong_slave_id_times_out(fake: FakeGripper) -> None:
    g = RobotiqGripper(fake.port, slave_id=10, timeout_s=0.2, retries=0)
    with pytest.raises(DeviceTimeoutError, match="slave 10"):
        g.connect()
    assert fake.requests_seen == 0


def test_tcp_link_is_a_pyserial_url_and_a_dropped_relay_is_reopened() -> None:
    """The controller's relay drops its client (a controller reboot): the request that finds
    the connection closed fails as a lost link, the next one connects again."""
    with FakeGripper(activation_time_s=0.1, transport="tcp") as fake:
        assert fake.port.startswith("socket://127.0.0.1:")
        g = RobotiqGripper(fake.port, timeout_s=0.3, retries=0)
        g.connect()
        g.activate()
        assert fake._client is not None
        fake._client.shutdown(socket.SHUT_RDWR)  # the relay's side closes
        with pytest.raises((ConnectionLostError, DeviceTimeoutError)):
            g.status()
        assert g.status().activated  # reopened: the gripper kept its state
        g.disconnect()


def test_tcp_link_refuses_a_symlink() -> None:
    with pytest.raises(ValueError, match="pty"):
        FakeGripper(link="/tmp/gripper-link", transport="tcp")


def test_tcp_link_with_no_relay_listening_is_a_lost_link() -> None:
    with socket.create_server(("127.0.0.1", 0)) as s:
        port = s.getsockname()[1]
    g = RobotiqGripper(f"socket://127.0.0.1:{port}", timeout_s=0.2, retries=0)
    with pytest.raises(ConnectionLostError, match="cannot open"):
        g.connect()
