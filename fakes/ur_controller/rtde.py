"""RTDE (port 30004) as a UR e-Series controller speaks it: codec and server.

Wire facts (UR's RTDE guide, protocol version 2, and ur_rtde 1.6.5's decoder): every package is
``uint16 size (incl. header) + uint8 type`` big-endian, then the payload. Setup replies carry a
recipe id and the comma-separated types; ``NOT_FOUND`` marks an unknown output and ``IN_USE`` an
input register owned by another connection (recipe id 0 then). Data packages are the recipe id
and the values packed at the exact widths of their types. Input recipe ids are per connection
and count from 1, because the client hard-codes them in the order it set them up.
"""

from __future__ import annotations

import itertools
import logging
import re
import socket
import struct
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass

from fakes.ur_controller.registers import NUM_REGISTERS, ControllerView, RegisterFile
from fakes.ur_controller.tcp import TcpService, send_all

log = logging.getLogger(__name__)

RTDE_PORT = 30004
HEADER = struct.Struct(">HB")

REQUEST_PROTOCOL_VERSION = 86  # 'V'
GET_URCONTROL_VERSION = 118  # 'v'
TEXT_MESSAGE = 77  # 'M'
DATA_PACKAGE = 85  # 'U'
CONTROL_PACKAGE_SETUP_OUTPUTS = 79  # 'O'
CONTROL_PACKAGE_SETUP_INPUTS = 73  # 'I'
CONTROL_PACKAGE_START = 83  # 'S'
CONTROL_PACKAGE_PAUSE = 80  # 'P'

PROTOCOL_VERSION = 2
MAX_FREQUENCY_HZ = 500.0
# text message warning levels
LEVEL_EXCEPTION, LEVEL_ERROR, LEVEL_WARNING, LEVEL_INFO = 0, 1, 2, 3

TYPE_FORMATS = {
    "VECTOR6D": "6d",
    "VECTOR3D": "3d",
    "VECTOR6INT32": "6i",
    "VECTOR6UINT32": "6I",
    "DOUBLE": "d",
    "UINT64": "Q",
    "UINT32": "I",
    "INT32": "i",
    "UINT8": "B",
    "BOOL": "?",
}


def encode(msg_type: int, payload: bytes = b"") -> bytes:
    """One RTDE package: header + payload."""
    return HEADER.pack(HEADER.size + len(payload), msg_type) + payload


def encode_text(message: str, source: str = "URControl", level: int = LEVEL_INFO) -> bytes:
    """Protocol-2 text message: uint8-prefixed message and source, then the warning level."""
    m = message.encode()[:255]
    s = source.encode()[:255]
    return encode(TEXT_MESSAGE, bytes([len(m)]) + m + bytes([len(s)]) + s + bytes([level]))


class PackageReader:
    """Splits a byte stream into (type, payload) packages."""

    def __init__(self) -> None:
        self._buf = bytearray()

    def feed(self, data: bytes) -> list[tuple[int, bytes]]:
        self._buf.extend(data)
        out: list[tuple[int, bytes]] = []
        while len(self._buf) >= HEADER.size:
            size, msg_type = HEADER.unpack_from(self._buf)
            if size < HEADER.size:
                raise ValueError(f"RTDE package size {size} is shorter than its header")
            if len(self._buf) < size:
                break
            out.append((msg_type, bytes(self._buf[HEADER.size:size])))
            del self._buf[:size]
        return out


# -- variables ---------------------------------------------------------------------------------

Getter = Callable[[ControllerView], object]
_V6_ZERO = (0.0,) * 6


_OUTPUTS: dict[str, tuple[str, Getter]] = {
    "timestamp": ("DOUBLE", lambda v: v.snap.timestamp_s),
    "target_q": ("VECTOR6D", lambda v: v.snap.target_q),
    "target_qd": ("VECTOR6D", lambda v: v.snap.target_qd),
    "target_qdd": ("VECTOR6D", lambda v: v.snap.target_qdd),
    "target_current": ("VECTOR6D", lambda v: v.snap.actual_current_a),
    "target_moment": ("VECTOR6D", lambda v: _V6_ZERO),
    "actual_q": ("VECTOR6D", lambda v: v.snap.q),
    "actual_qd": ("VECTOR6D", lambda v: v.snap.qd),
    "actual_current": ("VECTOR6D", lambda v: v.snap.actual_current_a),
    "actual_current_as_torque": ("VECTOR6D", lambda v: _V6_ZERO),
    "joint_control_output": ("VECTOR6D", lambda v: v.snap.actual_current_a),
    "actual_TCP_pose": ("VECTOR6D", lambda v: v.snap.tcp_pose),
    "actual_TCP_speed": ("VECTOR6D", lambda v: v.snap.tcp_speed),
    "actual_TCP_force": ("VECTOR6D", lambda v: v.snap.tcp_force),
    "target_TCP_pose": ("VECTOR6D", lambda v: v.snap.target_tcp_pose),
    "target_TCP_speed": ("VECTOR6D", lambda v: v.snap.target_tcp_speed),
    "actual_digital_input_bits": ("UINT64", lambda v: 0),
    "joint_temperatures": ("VECTOR6D", lambda v: v.snap.joint_temperatures_c),
    "actual_execution_time": ("DOUBLE", lambda v: 0.25),
    "robot_mode": ("INT32", lambda v: int(v.snap.robot_mode)),
    "joint_mode": ("VECTOR6INT32", lambda v: v.snap.joint_modes),
    "safety_mode": ("INT32", lambda v: int(v.snap.safety_mode)),
    "safety_status": ("INT32", lambda v: int(v.snap.safety_mode)),
    "actual_tool_accelerometer": ("VECTOR3D", lambda v: (0.0, 0.0, 9.81)),
    "speed_scaling": ("DOUBLE", lambda v: v.snap.speed_scaling),
    "target_speed_fraction": ("DOUBLE", lambda v: v.snap.target_speed_fraction),
    "actual_momentum": ("DOUBLE", lambda v: 0.0),
    "actual_main_voltage": ("DOUBLE", lambda v: 48.0),
    "actual_robot_voltage": ("DOUBLE", lambda v: 48.0 if v.snap.robot_mode >= 4 else 0.0),
    "actual_robot_current": ("DOUBLE", lambda v: sum(abs(c) for c in v.snap.actual_current_a)),
    "actual_joint_voltage": ("VECTOR6D", lambda v: (48.0,) * 6),
    "actual_digital_output_bits": ("UINT64", lambda v: v.regs.digital_output_bits()),
    "runtime_state": ("UINT32", lambda v: v.runtime_state),
    "robot_status_bits": ("UINT32", lambda v: int(v.snap.robot_status_bits)),
    "safety_status_bits": ("UINT32", lambda v: int(v.snap.safety_status_bits)),
    "standard_analog_input0": ("DOUBLE", lambda v: 0.0),
    "standard_analog_input1": ("DOUBLE", lambda v: 0.0),
    "standard_analog_output0": ("DOUBLE", lambda v: v.regs.analog_out[0]),
    "standard_analog_output1": ("DOUBLE", lambda v: v.regs.analog_out[1]),
    "tcp_force_scalar": ("DOUBLE", lambda v: 0.0),
    "ft_raw_wrench": ("VECTOR6D", lambda v: _V6_ZERO),
    "payload": ("DOUBLE", lambda v: v.regs.payload_kg),
    "payload_cog": ("VECTOR3D", lambda v: v.regs.payload_cog_m),
    "payload_inertia": ("VECTOR6D", lambda v: _V6_ZERO),
    "output_bit_registers0_to_31": ("UINT32", lambda v: v.regs.out_bits & 0xFFFFFFFF),
    "output_bit_registers32_to_63": ("UINT32", lambda v: (v.regs.out_bits >> 32) & 0xFFFFFFFF),
    "input_bit_registers0_to_31": ("UINT32", lambda v: v.regs.in_bits & 0xFFFFFFFF),
    "input_bit_registers32_to_63": ("UINT32", lambda v: (v.regs.in_bits >> 32) & 0xFFFFFFFF),
    # simulated: the arm's state
    "elbow_position": ("VECTOR3D", lambda v: v.snap.elbow_position),
    "elbow_velocity": ("VECTOR3D", lambda v: v.snap.elbow_velocity),
    "tcp_offset": ("VECTOR6D", lambda v: v.snap.tcp_offset),
    "actual_current_window": ("VECTOR6D", lambda v: tuple(abs(c) for c in v.snap.actual_current_a)),
    "actual_configurable_digital_output_bits": ("UINT64", lambda v: v.regs.configurable_do),
    "tool_output_mode": ("UINT8", lambda v: 0),  # 0: digital outputs, not a tool serial link
    "tool_digital_output0_mode": ("UINT8", lambda v: 1),  # 1: sinking (NPN), UR's default
    "tool_digital_output1_mode": ("UINT8", lambda v: 1),
    "script_control_line": ("UINT32", lambda v: 0),
    # constant: no dynamics, contact, tool electronics or Euromap67 board are simulated
    "joint_position_deviation_ratio": ("DOUBLE", lambda v: 0.0),
    "collision_detection_ratio": ("DOUBLE", lambda v: 0.0),
    "dexterity": ("DOUBLE", lambda v: 1.0),
    "io_current": ("DOUBLE", lambda v: 0.1),
    "tool_mode": ("UINT32", lambda v: 253 if v.snap.robot_mode >= 4 else 0),
    "analog_io_types": ("UINT32", lambda v: 0),
    "tool_analog_input_types": ("UINT32", lambda v: 0),
    "tool_analog_input0": ("DOUBLE", lambda v: 0.0),
    "tool_analog_input1": ("DOUBLE", lambda v: 0.0),
    "tool_output_voltage": ("INT32", lambda v: 24 if v.snap.robot_mode >= 4 else 0),
    "tool_output_voltage_2": ("INT32", lambda v: 0),
    "tool_output_current": ("DOUBLE", lambda v: 0.0),
    "tool_output_current_2": ("DOUBLE", lambda v: 0.0),
    "tool_temperature": ("DOUBLE", lambda v: 30.0 if v.snap.robot_mode >= 4 else 25.0),
    "euromap67_input_bits": ("UINT32", lambda v: 0),
    "euromap67_output_bits": ("UINT32", lambda v: 0),
    "euromap67_24V_voltage": ("DOUBLE", lambda v: 0.0),
    "euromap67_24V_current": ("DOUBLE", lambda v: 0.0),
    "actual_configurable_digital_input_bits": ("UINT64", lambda v: 0),
    "encoder0_raw": ("INT32", lambda v: 0),
    "encoder1_raw": ("INT32", lambda v: 0),
    "time_scale_source": ("UINT32", lambda v: 0),
    "external_force_torque": ("VECTOR6D", lambda v: v.regs.external_ft),
}

_REGISTER_NAME = re.compile(r"(input|output)_(int|double|bit)_register_(\d+)$")


def _register_getter(direction: str, kind: str, index: int) -> tuple[str, Getter] | None:
    if kind == "bit":
        if not 64 <= index < 128:
            return None
        if direction == "input":
            return "BOOL", lambda v: bool((v.regs.in_bits >> index) & 1)
        return "BOOL", lambda v: bool((v.regs.out_bits >> index) & 1)
    if not 0 <= index < NUM_REGISTERS:
        return None
    if kind == "int":
        table = "in_int" if direction == "input" else "out_int"
        return "INT32", lambda v: getattr(v.regs, table)[index]
    table = "in_double" if direction == "input" else "out_double"
    return "DOUBLE", lambda v: getattr(v.regs, table)[index]


def output_variable(name: str) -> tuple[str, Getter] | None:
    """(type, getter) of an output variable, or None when the controller has no such name."""
    if name in _OUTPUTS:
        return _OUTPUTS[name]
    m = _REGISTER_NAME.match(name)
    return _register_getter(m[1], m[2], int(m[3])) if m else None


Setter = Callable[[RegisterFile, object], None]


def _set_list(table: str, index: int) -> Setter:
    def put(regs: RegisterFile, value: object) -> None:
        getattr(regs, table)[index] = value
        if table == "in_int":
            regs.in_int_written_s[index] = time.monotonic()

    return put


def _set_attr(attr: str) -> Setter:
    return lambda regs, value: setattr(regs, attr, value)


def _pending(name: str) -> Setter:
    """Masked I/O writes arrive as separate variables; they are folded in by apply_io."""
    return lambda regs, value: regs.pending_io.__setitem__(name, value)


def _set_bit(index: int) -> Setter:
    def put(regs: RegisterFile, value: object) -> None:
        regs.in_bits = (regs.in_bits & ~(1 << index)) | (int(bool(value)) << index)

    return put


def _set_bit_word(shift: int) -> Setter:
    def put(regs: RegisterFile, value: object) -> None:
        regs.in_bits = (regs.in_bits & ~(0xFFFFFFFF << shift)) | (int(value) << shift)  # type: ignore[call-overload]

    return put


_INPUTS: dict[str, tuple[str, Setter]] = {
    "standard_digital_output_mask": ("UINT8", _pending("standard_digital_output_mask")),
    "standard_digital_output": ("UINT8", _pending("standard_digital_output")),
    "configurable_digital_output_mask": ("UINT8", _pending("configurable_digital_output_mask")),
    "configurable_digital_output": ("UINT8", _pending("configurable_digital_output")),
    "tool_digital_output_mask": ("UINT8", _pending("tool_digital_output_mask")),
    "tool_digital_output": ("UINT8", _pending("tool_digital_output")),
    "speed_slider_mask": ("UINT32", _pending("speed_slider_mask")),
    "speed_slider_fraction": ("DOUBLE", _pending("speed_slider_fraction")),
    "standard_analog_output_mask": ("UINT8", _pending("standard_analog_output_mask")),
    "standard_analog_output_type": ("UINT8", _pending("standard_analog_output_type")),
    "standard_analog_output_0": ("DOUBLE", _pending("standard_analog_output_0")),
    "standard_analog_output_1": ("DOUBLE", _pending("standard_analog_output_1")),
    "external_force_torque": ("VECTOR6D", _set_attr("external_ft")),
    "input_bit_registers0_to_31": ("UINT32", _set_bit_word(0)),
    "input_bit_registers32_to_63": ("UINT32", _set_bit_word(32)),
}


def input_variable(name: str) -> tuple[str, Setter] | None:
    """(type, setter) of an input variable, or None when the controller has no such name."""
    if name in _INPUTS:
        return _INPUTS[name]
    m = _REGISTER_NAME.match(name)
    if not m or m[1] != "input":
        return None
    index = int(m[3])
    if m[2] == "bit":
        return ("BOOL", _set_bit(index)) if 64 <= index < 128 else None
    if not 0 <= index < NUM_REGISTERS:
        return None
    return ("INT32", _set_list("in_int", index)) if m[2] == "int" else (
        "DOUBLE", _set_list("in_double", index))


def _struct_for(types: list[str]) -> struct.Struct:
    return struct.Struct(">B" + "".join(TYPE_FORMATS[t] for t in types))


def _flatten(values: list[object]) -> list[object]:
    flat: list[object] = []
    for value in values:
        if isinstance(value, tuple | list):
            flat.extend(value)
        else:
            flat.append(value)
    return flat


@dataclass
class OutputRecipe:
    recipe_id: int
    frequency_hz: float
    getters: list[Getter]
    packer: struct.Struct

    def encode(self, view: ControllerView) -> bytes:
        values = _flatten([g(view) for g in self.getters])
        return encode(DATA_PACKAGE, self.packer.pack(self.recipe_id, *values))


@dataclass
class InputRecipe:
    recipe_id: int
    names: list[str]
    types: list[str]
    setters: list[Setter]
    unpacker: struct.Struct


_VECTOR_WIDTH = {"VECTOR6D": 6, "VECTOR3D": 3, "VECTOR6INT32": 6, "VECTOR6UINT32": 6}


class RTDEConnection:
    """One client connection: answers setup requests on its own thread; the controller's cycle
    thread sends its data packages through :meth:`publish`."""

    _ids = itertools.count(1)

    def __init__(self, sock: socket.socket, server: RTDEServer) -> None:
        self.id = next(self._ids)
        self.sock = sock
        self.server = server
        self.output: OutputRecipe | None = None
        self.inputs: dict[int, InputRecipe] = {}
        self.started = False
        self.closed = False
        self._next_due_s = 0.0
        self._send_lock = threading.Lock()
        self._reader = PackageReader()

    # -- sending -----------------------------------------------------------------------------
    def send(self, data: bytes) -> None:
        if not self.closed and not send_all(self.sock, data, self._send_lock):
            self.closed = True

    def package_if_due(self, view: ControllerView, now_s: float) -> bytes | None:
        """This connection's data package when its period has elapsed, else None."""
        # (a tenth of a cycle of tolerance: cycle times are sums of 2 ms steps, not exact)
        if (not self.started or self.closed or self.output is None
                or now_s < self._next_due_s - 2e-4):
            return None
        period = 1.0 / self.output.frequency_hz
        self._next_due_s = (now_s + period if self._next_due_s <= 0.0  # first after start
                            else max(self._next_due_s + period, now_s - period))
        return self.output.encode(view)

    # -- Handler -----------------------------------------------------------------------------
    def on_open(self) -> None:
        pass

    def on_close(self) -> None:
        self.closed = True
        self.server.regs.release(self.id)

    def feed(self, data: bytes) -> bool:
        for msg_type, payload in self._reader.feed(data):
            self._handle(msg_type, payload)
        return not self.closed

    def _handle(self, msg_type: int, payload: bytes) -> None:
        if msg_type == REQUEST_PROTOCOL_VERSION:
            (version,) = struct.unpack(">H", payload[:2])
            self.send(encode(REQUEST_PROTOCOL_VERSION, bytes([version == PROTOCOL_VERSION])))
        elif msg_type == GET_URCONTROL_VERSION:
            self.send(encode(GET_URCONTROL_VERSION, struct.pack(">IIII", *self.server.version)))
        elif msg_type == CONTROL_PACKAGE_SETUP_OUTPUTS:
            self._setup_outputs(payload)
        elif msg_type == CONTROL_PACKAGE_SETUP_INPUTS:
            self._setup_inputs(payload)
        elif msg_type == CONTROL_PACKAGE_START:
            ok = self.output is not None
            if ok:
                self._next_due_s = 0.0
                self.started = True
            self.send(encode(CONTROL_PACKAGE_START, bytes([ok])))
        elif msg_type == CONTROL_PACKAGE_PAUSE:
            self.started = False
            self.send(encode(CONTROL_PACKAGE_PAUSE, b"\x01"))
        elif msg_type == DATA_PACKAGE:
            self._data(payload)
        else:
            log.debug("rtde connection %d: ignoring package type %d", self.id, msg_type)

    def _setup_outputs(self, payload: bytes) -> None:
        (frequency,) = struct.unpack(">d", payload[:8])
        names = [n for n in payload[8:].decode(errors="replace").split(",") if n]
        found = [output_variable(n) for n in names]
        types = [f[0] if f else "NOT_FOUND" for f in found]
        valid = all(found) and bool(names) and 0.0 < frequency <= MAX_FREQUENCY_HZ
        recipe_id = 1 if valid else 0
        if valid:
            self.output = OutputRecipe(
                recipe_id, frequency, [f[1] for f in found if f], _struct_for(types))
        self.send(encode(CONTROL_PACKAGE_SETUP_OUTPUTS,
                         bytes([recipe_id]) + ",".join(types).encode()))

    def _setup_inputs(self, payload: bytes) -> None:
        names = [n for n in payload.decode(errors="replace").split(",") if n]
        found = [input_variable(n) for n in names]
        types = [f[0] if f else "NOT_FOUND" for f in found]
        recipe_id = 0
        if all(found) and names:
            taken = set(self.server.regs.claim(names, self.id))
            if taken:
                types = ["IN_USE" if n in taken else t for n, t in zip(names, types, strict=True)]
            else:
                recipe_id = len(self.inputs) + 1
                self.inputs[recipe_id] = InputRecipe(
                    recipe_id, names, types, [f[1] for f in found if f], _struct_for(types))
        self.send(encode(CONTROL_PACKAGE_SETUP_INPUTS,
                         bytes([recipe_id]) + ",".join(types).encode()))

    def _data(self, payload: bytes) -> None:
        if not payload:
            return
        recipe = self.inputs.get(payload[0])
        if recipe is None or len(payload) < recipe.unpacker.size:
            self.send(encode_text(f"RTDE: invalid data package for recipe {payload[0]}",
                                  level=LEVEL_ERROR))
            return
        # Trailing bytes beyond the recipe are ignored, as the controller does: ur_rtde sends
        # some commands with more doubles than their recipe holds.
        flat = list(recipe.unpacker.unpack_from(payload))[1:]
        regs = self.server.regs
        with regs.lock:
            for t, setter in zip(recipe.types, recipe.setters, strict=True):
                width = _VECTOR_WIDTH.get(t, 1)
                value: object = tuple(flat[:width]) if width > 1 else flat[0]
                del flat[:width]
                setter(regs, value)
            self.server.apply_io(regs)


class RTDEServer:
    """Listens on ``host:30004``; one :class:`RTDEConnection` per client."""

    def __init__(
        self, host: str, regs: RegisterFile, version: tuple[int, int, int, int],
        on_io: Callable[[RegisterFile], None] | None = None, port: int = RTDE_PORT,
    ) -> None:
        self.regs = regs
        self.version = version
        self._on_io = on_io
        self.service = TcpService(host, port, "rtde", lambda sock: RTDEConnection(sock, self))

    def connections(self) -> list[RTDEConnection]:
        return [h for h in self.service.handlers() if isinstance(h, RTDEConnection)]

    def apply_io(self, regs: RegisterFile) -> None:
        """Fold masked I/O writes (mask + value pairs) into the output image."""
        pending = regs.pending_io
        for kind, name in (("standard_do", "standard_digital_output"),
                           ("configurable_do", "configurable_digital_output"),
                           ("tool_do", "tool_digital_output")):
            mask = pending.pop(f"{name}_mask", None)
            value = pending.pop(name, None)
            if isinstance(mask, int) and isinstance(value, int):
                setattr(regs, kind, (getattr(regs, kind) & ~mask) | (value & mask))
        mask = pending.pop("standard_analog_output_mask", None)
        pending.pop("standard_analog_output_type", None)
        for i in (0, 1):
            value = pending.pop(f"standard_analog_output_{i}", None)
            if isinstance(mask, int) and mask & (1 << i) and isinstance(value, float):
                regs.analog_out[i] = value
        if self._on_io is not None:
            self._on_io(regs)

    def due_packages(self, view: ControllerView, now_s: float
                     ) -> list[tuple[RTDEConnection, bytes]]:
        """Encode (under the register lock) what is due; send with :meth:`send_packages`."""
        if self.service.frozen:
            return []
        due = [(c, c.package_if_due(view, now_s)) for c in self.connections()]
        return [(c, data) for c, data in due if data is not None]

    @staticmethod
    def send_packages(packages: list[tuple[RTDEConnection, bytes]]) -> None:
        for conn, data in packages:
            conn.send(data)

    def any_streaming(self) -> bool:
        return any(c.started and not c.closed for c in self.connections())

    def broadcast_text(self, message: str, level: int = LEVEL_INFO) -> None:
        data = encode_text(message, level=level)
        for conn in self.connections():
            if conn.started:
                conn.send(data)
