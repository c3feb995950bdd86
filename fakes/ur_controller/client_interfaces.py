"""The primary (30001), secondary (30002) and real-time (30003) client interfaces.

Byte layouts follow UR's "Primary and Secondary Interfaces" and "Real-Time Interface" guides
for e-Series software 5.x (all big-endian; every message and sub-package starts with an int32
length that includes itself, then a type byte):

- primary and secondary, 10 Hz: on connect a version message (type 20, robot message type 3),
  then robot state messages (type 16) with the sub-packages RobotModeData (0, 47 bytes),
  JointData (1, 251), ToolData (2, 37), MasterboardData (3, 74), CartesianInfo (4, 101),
  KinematicsInfo (5, 225), ForceModeData (7, 61) and AdditionalInfo (8, 9). The configuration,
  calibration, safety and tool-communication packages (6, 9, 10, 11, ...) are not sent; UR
  notes clients must expect packages to be absent.
- real-time, 500 Hz: the 1116-byte package (message size + 139 doubles, "Time" through
  "Safety Status"); the fields later 5.x releases append after "Safety Status" are not sent
  (the message size says so).

All three ports accept URScript; each complete program (a ``def``/``sec`` block or a single
statement line) is handed to the controller. A client that does not read (ur_rtde's script
client never does) gets whole packages dropped, never a torn one, and never stalls the cycle.
"""

from __future__ import annotations

import contextlib
import math
import select
import socket
import struct
import threading
from collections.abc import Callable
from typing import Literal

from fakes.ur_controller.registers import ControllerView
from fakes.ur_controller.tcp import TcpService
from fakes.ur_controller.urscript import split_programs
from fakes.ur_sim import RobotMode, SafetyMode
from fakes.ur_sim.kinematics import UR5E

PRIMARY_PORT, SECONDARY_PORT, REALTIME_PORT = 30001, 30002, 30003
MESSAGE_ROBOT_STATE, MESSAGE_ROBOT_MESSAGE = 16, 20
ROBOT_MESSAGE_VERSION = 3
STATE_PERIOD_S = 0.1
_MAX_PENDING_BYTES = 64 * 1024

Kind = Literal["primary", "secondary", "realtime"]


def _sub(ptype: int, fmt: str, *values: object) -> bytes:
    body = struct.pack(">" + fmt, *values)
    return struct.pack(">iB", 5 + len(body), ptype) + body


def _message(mtype: int, body: bytes) -> bytes:
    return struct.pack(">iB", 5 + len(body), mtype) + body


def version_message(version: tuple[int, int, int, int], timestamp_us: int) -> bytes:
    """Robot message type 3: project name, major, minor, bugfix, build and build date."""
    name = b"URControl"
    body = (struct.pack(">QbB", timestamp_us, -2, ROBOT_MESSAGE_VERSION)
            + struct.pack(">b", len(name)) + name
            + struct.pack(">BBii", version[0], version[1], version[2], version[3])
            + b"15-10-2021, 12:00:00")
    return _message(MESSAGE_ROBOT_MESSAGE, body)


def robot_state_message(view: ControllerView) -> bytes:
    """One robot state message (type 16) with the sub-packages listed in the module doc."""
    s, regs = view.snap, view.regs
    powered = s.robot_mode in (RobotMode.POWER_ON, RobotMode.IDLE, RobotMode.RUNNING)
    estop = s.safety_mode in (SafetyMode.ROBOT_EMERGENCY_STOP, SafetyMode.SYSTEM_EMERGENCY_STOP)
    running = bool(s.robot_status_bits & 2)
    ts_us = int(s.timestamp_s * 1e6)
    parts = [_sub(0, "Q???????BBdddB", ts_us, True, True, powered, estop,
                  s.safety_mode == SafetyMode.PROTECTIVE_STOP, running,
                  view.runtime_state == 4, int(s.robot_mode), 0,
                  s.target_speed_fraction, s.speed_scaling, 1.0, 0)]
    joint_fields: list[object] = []
    for i in range(6):
        joint_fields += [s.q[i], s.target_q[i], s.qd[i], s.actual_current_a[i],
                         48.0 if powered else 0.0, s.joint_temperatures_c[i], 0.0,
                         s.joint_modes[i]]
    parts.append(_sub(1, "dddffffB" * 6, *joint_fields))
    parts.append(_sub(2, "BBddfBffB", 0, 0, 0.0, 0.0, 24.0 if powered else 0.0, 0,
                      0.0, 30.0 if powered else 25.0, 253 if powered else 0))
    parts.append(_sub(3, "iiBBddBBddffffBBBIBB", 0, regs.digital_output_bits() & 0xFFFF,
                      0, 0, 0.0, 0.0, 0, 0, regs.analog_out[0], regs.analog_out[1],
                      35.0, 48.0 if powered else 0.0,
                      float(sum(abs(c) for c in s.actual_current_a)), 0.1,
                      int(s.safety_mode), int(s.safety_mode == SafetyMode.REDUCED), 0, 0, 0, 0))
    parts.append(_sub(4, "d" * 12, *s.tcp_pose, *s.tcp_offset))
    dh = UR5E
    parts.append(_sub(5, "IIIIII" + "d" * 24 + "I", *([0] * 6), *([0.0] * 6),
                      *(a / 1000.0 for a in dh.a_mm), *(d / 1000.0 for d in dh.d_mm),
                      *dh.alpha_rad, 0))
    parts.append(_sub(7, "d" * 7, *s.tcp_force, 1.0))
    parts.append(_sub(8, "B??B", 0, False, False, 0))
    return _message(MESSAGE_ROBOT_STATE, b"".join(parts))


_REALTIME = struct.Struct(">i" + "d" * 139)


def realtime_package(view: ControllerView) -> bytes:
    """The real-time interface's package (1116 bytes)."""
    s, regs = view.snap, view.regs
    powered = s.robot_mode in (RobotMode.POWER_ON, RobotMode.IDLE, RobotMode.RUNNING)
    momentum = math.sqrt(sum(v * v for v in s.tcp_speed[:3]))
    program_state = 2.0 if s.robot_status_bits & 2 else 1.0
    values = [
        s.timestamp_s, *s.target_q, *s.target_qd, *s.target_qdd, *s.actual_current_a,
        *(0.0,) * 6, *s.q, *s.qd, *s.actual_current_a, *s.actual_current_a,
        *s.tcp_pose, *s.tcp_speed, *s.tcp_force, *s.target_tcp_pose, *s.target_tcp_speed,
        0.0, *s.joint_temperatures_c, 0.00025, 0.0, float(s.robot_mode),
        *(float(m) for m in s.joint_modes), float(s.safety_mode), *(0.0,) * 6,
        0.0, 0.0, 9.81, *(0.0,) * 6, s.speed_scaling, momentum, 0.0, 0.0, 48.0,
        48.0 if powered else 0.0, float(sum(abs(c) for c in s.actual_current_a)),
        *((48.0,) * 6 if powered else (0.0,) * 6), float(regs.digital_output_bits()),
        program_state, *s.elbow_position, *s.elbow_velocity, float(s.safety_status_bits),
    ]
    return _REALTIME.pack(_REALTIME.size, *values)


class ClientSession:
    """One client of 30001/30002/30003: receives URScript, is sent state packages."""

    def __init__(self, sock: socket.socket, kind: Kind, on_program: Callable[[str], None],
                 greeting: bytes | None) -> None:
        self.sock = sock
        self.kind = kind
        self._on_program = on_program
        self._greeting = greeting
        self._buffer = ""
        # The greeting is queued before the session is registered, so the controller cycle's
        # first state package cannot overtake it (it did on a loaded host: the session is
        # published to from the moment it is accepted, on_open runs later in its own thread).
        self._pending = greeting or b""
        self._lock = threading.Lock()
        self.closed = False
        self.next_due_s = 0.0
        self.dropped = 0

    def on_open(self) -> None:
        self.send(b"")  # flush the queued greeting, if the controller cycle has not already

    def feed(self, data: bytes) -> bool:
        self._buffer += data.decode(errors="replace")
        programs, self._buffer = split_programs(self._buffer)
        for program in programs:
            self._on_program(program)
        return True

    def on_close(self) -> None:
        self.closed = True

    def backlogged(self) -> bool:
        """Still more than the limit queued after trying to send it."""
        if len(self._pending) <= _MAX_PENDING_BYTES:
            return False
        self.send(b"")
        return len(self._pending) > _MAX_PENDING_BYTES

    def send(self, data: bytes) -> None:
        """Queue a whole package; dropped whole when the client is not reading."""
        with self._lock:
            if self.closed:
                return
            if len(self._pending) > _MAX_PENDING_BYTES:
                self.dropped += 1 if data else 0
            else:
                self._pending += data
            if not self._pending:
                return
            try:
                _, writable, _ = select.select([], [self.sock], [], 0)
                if not writable:
                    return  # the socket buffer is full: never wait in the controller cycle
                n = self.sock.send(self._pending)
            except (BlockingIOError, TimeoutError):
                return
            except (OSError, ValueError):
                self.closed = True
                return
            self._pending = self._pending[n:]


class ClientInterfaces:
    """The three services; the controller cycle calls :meth:`publish` every cycle."""

    def __init__(self, host: str, on_program: Callable[[str], None],
                 version: tuple[int, int, int, int],
                 ports: tuple[int, int, int] = (PRIMARY_PORT, SECONDARY_PORT, REALTIME_PORT)
                 ) -> None:
        self._version = version
        greeting = version_message(version, 0)
        self.services = {
            "primary": TcpService(host, ports[0], "primary", lambda sock: ClientSession(
                sock, "primary", on_program, greeting)),
            "secondary": TcpService(host, ports[1], "secondary", lambda sock: ClientSession(
                sock, "secondary", on_program, greeting)),
            "realtime": TcpService(host, ports[2], "realtime", lambda sock: ClientSession(
                sock, "realtime", on_program, None)),
        }

    def sessions(self) -> list[ClientSession]:
        out: list[ClientSession] = []
        for service in self.services.values():
            if not service.frozen:
                out += [h for h in service.handlers() if isinstance(h, ClientSession)]
        return out

    def any_realtime(self) -> bool:
        return any(s.kind == "realtime" and not s.closed for s in self.sessions())

    def publish(self, view: ControllerView, now_s: float) -> None:
        """Send what is due at controller time ``now_s``."""
        state: bytes | None = None
        rt: bytes | None = None
        for session in self.sessions():
            if session.closed or now_s < session.next_due_s - 2e-4:
                continue
            if session.kind == "realtime":
                if session.backlogged():
                    session.dropped += 1  # a client that does not read (ur_rtde's script one)
                    continue
                rt = rt if rt is not None else realtime_package(view)
                session.send(rt)
                continue
            session.next_due_s = max(session.next_due_s + STATE_PERIOD_S, now_s - STATE_PERIOD_S)
            state = state if state is not None else robot_state_message(view)
            session.send(state)

    def close(self, reset: bool = False) -> None:
        for service in self.services.values():
            service.frozen = False
            with contextlib.suppress(OSError):
                service.close(reset)
