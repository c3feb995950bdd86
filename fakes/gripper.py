"""A simulated Robotiq 2F-85 answering Modbus RTU on a pseudo-terminal.

The real adapter (:class:`drivers.robotiq.RobotiqGripper`) talks to it through a real serial
device, so the framing, timing and error paths under test are the ones a cell sees. pymodbus
decodes requests and encodes answers (framing, CRC); this module holds the gripper's behaviour:
activation takes time, the fingers move at the speed ``rSP`` asks for in real time, a part they
close on (:class:`Grasp`: the simulated world's parts, or a bench piece of a fixed width) stops
them and sets ``gOBJ`` (2: stopped on an object while closing; 3: at the requested position,
nothing touched), and faults can be injected (garbage or a wrong CRC instead of an answer,
silence, an answer later than the client waits for, a device fault code).

Two links, as a cell has them: a pseudo-terminal (a USB-RS-485 adapter's serial device), or
a raw TCP stream (``socket://HOST:PORT``), as a UR e-Series controller relays the RS-485 of a
gripper on its tool flange (the rs485 URCap serves it on port 54321). A pty's bytes pass
through the kernel's tty work items, which a host whose cores are busy at the same nice
value can hold back for a second; a TCP stream on loopback does not wait on them.

``python -m fakes.gripper --link PATH`` (or ``--tcp [HOST:]PORT``) serves until killed.
"""

from __future__ import annotations

import argparse
import contextlib
import os
import select
import signal
import socket
import sys
import threading
import time
import tty
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Literal, Protocol

from pymodbus.framer import FramerRTU
from pymodbus.pdu import DecodePDU, ExceptionResponse, ModbusPDU
from pymodbus.pdu.register_message import (
    ReadHoldingRegistersResponse,
    ReadInputRegistersResponse,
    ReadWriteMultipleRegistersRequest,
    ReadWriteMultipleRegistersResponse,
    WriteMultipleRegistersResponse,
)

from drivers.robotiq import (
    ACTION_REQUEST_ADDR,
    DEFAULT_SLAVE_ID,
    GOBJ_AT_REQUEST,
    GOBJ_CONTACT_CLOSING,
    GOBJ_MOVING,
    GRIPPER_STATUS_ADDR,
    GSTA_ACTIVATED,
    GSTA_ACTIVATING,
    GSTA_RESET,
    N_REGISTERS,
    RACT,
    RGTO,
    STROKE_MM,
    mm_to_position,
)

LineFault = Literal["garbage", "bad_crc", "no_answer", "late"]
Transport = Literal["pty", "tcp"]
LATE_ANSWER_S = 0.6  # how long a "late" answer keeps the gripper (and the requests after it)

MIN_SPEED_MM_S = 20.0  # 2F-85 datasheet: 20..150 mm/s finger speed
MAX_SPEED_MM_S = 150.0
ILLEGAL_FUNCTION = 0x01
ILLEGAL_ADDRESS = 0x02
FRAME_GAP_S = 0.05  # silence that drops a half-received frame (RTU's 3.5 chars, lenient)


# The position scale of the manual's register description: gPO/rPR 0x00 is fully open (85 mm),
# 0xFF fully closed, linear over the stroke. A real gripper's fingers stop at software limits
# inside that range (the manual's example reads 0x0D after a full opening request); the model
# takes those limits as parameters, by default the whole range.
POS_OPEN_LIMIT = 0x00
POS_CLOSED_LIMIT = 0xFF
MANUAL_EXAMPLE_OPEN_LIMIT = 0x0D
MM_PER_BIT = STROKE_MM / 255.0


def finger_position(opening_mm: float) -> float:
    """Position units (gPO) at which the fingers are ``opening_mm`` apart."""
    return float(mm_to_position(opening_mm))


def opening_mm(position: float) -> float:
    """How far apart the fingers are (mm) at ``position`` units (gPO)."""
    return STROKE_MM - position * MM_PER_BIT


def speed_units_per_s(rsp: int) -> float:
    """Finger speed for an ``rSP`` byte, in position units (1/255 of the stroke) per second."""
    mm_s = MIN_SPEED_MM_S + (MAX_SPEED_MM_S - MIN_SPEED_MM_S) * rsp / 255.0
    return mm_s / MM_PER_BIT


class Grasp(Protocol):
    """What lies between the fingers: asked when they start to close, told when they open."""

    def grip(self, opening_mm: float, closing_to_mm: float) -> float | None:
        """Fingers ``opening_mm`` apart start closing towards ``closing_to_mm``: the width of
        the part they will stop on (held from now on), or None (nothing in their way)."""
        ...

    def release(self) -> None:
        """The fingers open: whatever they held is let go."""
        ...


@dataclass(frozen=True)
class BenchPiece:
    """A test piece clamped on a bench gripper: always between the fingers, ``width_mm``
    wide (a gripper served on its own, with no simulated world around it)."""

    width_mm: float

    def grip(self, opening_mm: float, closing_to_mm: float) -> float | None:
        return self.width_mm if closing_to_mm < self.width_mm <= opening_mm + 1e-9 else None

    def release(self) -> None:
        return None


@dataclass
class _Motion:
    start_pos: float
    target: int
    units_s: float
    start_s: float
    stop_at: float | None  # position where an object stops the fingers


class GripperModel:
    """The register-level behaviour, independent of the wire; time comes from ``clock``."""

    def __init__(
        self, activation_time_s: float = 0.5, grasp: Grasp | None = None,
        clock: Callable[[], float] = time.monotonic,
        limits: tuple[int, int] = (POS_OPEN_LIMIT, POS_CLOSED_LIMIT),
    ) -> None:
        self.activation_time_s = activation_time_s
        self.grasp = grasp
        self.open_limit, self.closed_limit = limits
        self._clock = clock
        self.request = [0, 0, 0, 0, 0, 0]  # the six action-request bytes
        self._activate_started: float | None = None
        self._pos = 0.0
        self._motion: _Motion | None = None
        self._gobj = GOBJ_AT_REQUEST
        self.fault = 0
        self.lock = threading.RLock()

    def now(self) -> float:
        return self._clock()

    def set_grasp(self, grasp: Grasp | None) -> None:
        """What the fingers close on from the next motion on (None: nothing)."""
        with self.lock:
            self.grasp = grasp

    def inject_fault(self, gflt: int) -> None:
        """Raise a device fault (e.g. 0x0E overcurrent): motion stops until a reset."""
        with self.lock:
            self._update()
            self._motion = None
            self.fault = gflt

    # -- time evolution --------------------------------------------------------------------
    def _gsta(self) -> int:
        if not self.request[0] & RACT or self._activate_started is None:
            return GSTA_RESET
        if self.now() - self._activate_started < self.activation_time_s:
            return GSTA_ACTIVATING
        return GSTA_ACTIVATED

    def _update(self) -> None:
        m = self._motion
        if m is None:
            return
        direction = 1.0 if m.target >= m.start_pos else -1.0
        travelled = (self.now() - m.start_s) * m.units_s
        pos = m.start_pos + direction * travelled
        if m.stop_at is not None and pos >= m.stop_at:
            self._pos, self._gobj, self._motion = m.stop_at, GOBJ_CONTACT_CLOSING, None
        elif (pos - m.target) * direction >= 0:
            self._pos, self._gobj, self._motion = float(m.target), GOBJ_AT_REQUEST, None
        else:
            self._pos, self._gobj = pos, GOBJ_MOVING

    def _start_motion(self) -> None:
        rsp = self.request[4]
        target = min(max(self.request[3], self.open_limit), self.closed_limit)
        stop_at = None
        if self.grasp is not None:
            if target > self._pos:
                width_mm = self.grasp.grip(opening_mm(self._pos), opening_mm(target))
                if width_mm is not None:
                    stop_at = min(max(finger_position(width_mm), self._pos), float(target))
            elif target < self._pos:
                self.grasp.release()
        self._motion = _Motion(self._pos, target, speed_units_per_s(rsp), self.now(), stop_at)
        self._gobj = GOBJ_MOVING

    # -- registers -------------------------------------------------------------------------
    def write_request(self, offset: int, registers: list[int]) -> None:
        with self.lock:
            self._update()
            new = list(self.request)
            for i, r in enumerate(registers):
                new[2 * (offset + i)] = (r >> 8) & 0xFF
                new[2 * (offset + i) + 1] = r & 0xFF
            was_active = bool(self.request[0] & RACT)
            self.request = new
            if not new[0] & RACT:  # reset: clears faults, the fingers stay where they are
                self._activate_started, self._motion, self.fault = None, None, 0
                self._gobj = GOBJ_AT_REQUEST
                if new[0] & RGTO:
                    self.fault = 0x07
                return
            if not was_active:
                self._activate_started = self.now()
                self._pos = float(self.open_limit)  # activation runs a full stroke, ends open
                if self.grasp is not None:
                    self.grasp.release()
            if not new[0] & RGTO:
                self._motion = None
                return
            gsta = self._gsta()
            if gsta != GSTA_ACTIVATED:
                self.fault = 0x05 if gsta == GSTA_ACTIVATING else 0x07
                return
            if self.fault in (0x05, 0x07):
                self.fault = 0
            if self.fault == 0:
                self._start_motion()

    def status_bytes(self) -> list[int]:
        with self.lock:
            self._update()
            gsta = self._gsta()
            if self.fault == 0x05 and gsta == GSTA_ACTIVATED and self.request[0] & RGTO:
                self.fault = 0  # the delayed action now runs, as on the real gripper
                self._start_motion()
                self._update()
            act = self.request[0] & RACT
            gto = 1 if self.request[0] & RGTO else 0
            # gOBJ is only meaningful with gGTO = 1 (the manual: "ignore if gGTO == 0"); the
            # gripper reports 0 then, so an activated, idle gripper reads 0x31 as in its example
            gobj = self._gobj if gsta == GSTA_ACTIVATED and gto else GOBJ_MOVING
            moving = self._motion is not None
            current = 0x0A if moving else (self.request[5] // 4 if gobj == 2 else 0)
            status = act | (gto << 3) | (gsta << 4) | (gobj << 6)
            return [status, 0, self.fault, self.request[3], round(self._pos), current]

    def read_registers(self, address: int, count: int) -> list[int] | None:
        """Status (0x07D0) or action-request read-back (0x03E8); None for other addresses."""
        def inside(base: int) -> bool:
            return base <= address and address + count <= base + N_REGISTERS

        if inside(GRIPPER_STATUS_ADDR):
            data, offset = self.status_bytes(), address - GRIPPER_STATUS_ADDR
        elif inside(ACTION_REQUEST_ADDR):
            with self.lock:
                data, offset = list(self.request), address - ACTION_REQUEST_ADDR
        else:
            return None
        return [(data[2 * i] << 8) | data[2 * i + 1] for i in range(offset, offset + count)]


class FakeGripper:
    """Serves a :class:`GripperModel` as Modbus RTU slave ``slave_id`` on a pseudo-terminal
    (``transport="pty"``) or on a TCP relay at ``tcp_host`` (``"tcp"``: one client at a
    time, a new connection replaces the old one, as the controller's relay does).

    ``port`` is what a client opens: ``link`` when given, else the pty's own name; for TCP a
    pyserial URL, ``socket://HOST:PORT``.
    """

    def __init__(
        self, link: str | Path | None = None, slave_id: int = DEFAULT_SLAVE_ID,
        activation_time_s: float = 0.5, grasp: Grasp | None = None,
        transport: Transport = "pty", tcp_host: str = "127.0.0.1", tcp_port: int = 0,
    ) -> None:
        if transport == "tcp" and link is not None:
            raise ValueError("a link (symlink to a serial device) needs transport='pty'")
        self.link = Path(link) if link is not None else None
        self.slave_id = slave_id
        self.transport = transport
        self._tcp_address = (tcp_host, tcp_port)
        self.model = GripperModel(activation_time_s, grasp)
        self._framer = FramerRTU(DecodePDU(is_server=True))
        self._line_faults: list[LineFault] = []
        self._master = self._slave = -1
        self._slave_name = ""
        self._listener: socket.socket | None = None
        self._client: socket.socket | None = None
        self._thread: threading.Thread | None = None
        self._stop = threading.Event()
        self.requests_seen = 0

    @property
    def port(self) -> str:
        """What a client opens ("" before the first start picked a pty or a TCP port)."""
        if self.transport == "tcp":
            host, port = self._tcp_address
            return f"socket://{host}:{port}" if port else ""
        return str(self.link) if self.link is not None else self._slave_name

    def start(self) -> FakeGripper:
        if self.transport == "tcp":
            self._listener = socket.create_server(self._tcp_address)
            self._tcp_address = self._listener.getsockname()[:2]  # the port 0 chose
        else:
            self._master, self._slave = os.openpty()
            tty.setraw(self._slave)  # no echo, no line discipline: a plain 8-bit line
            self._slave_name = os.ttyname(self._slave)
            if self.link is not None:
                with contextlib.suppress(FileNotFoundError):
                    self.link.unlink()
                self.link.symlink_to(self._slave_name)
        self._stop.clear()
        self._thread = threading.Thread(target=self._serve, name="fake-gripper", daemon=True)
        self._thread.start()
        return self

    def stop(self) -> None:
        """Stop serving; the serving thread closes the line as it ends (a late answer it is
        sending finishes first), so no descriptor is closed under it."""
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=2.0)
            self._thread = None
        else:
            self._close_line()
        if self.link is not None and self.link.is_symlink():
            self.link.unlink()

    def _close_line(self) -> None:
        for fd in (self._master, self._slave):
            if fd >= 0:
                os.close(fd)
        self._master = self._slave = -1
        for sock in (self._client, self._listener):
            if sock is not None:
                sock.close()
        self._client = self._listener = None

    def __enter__(self) -> FakeGripper:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()

    def inject_line_fault(self, fault: LineFault, count: int = 1) -> None:
        """Answer the next ``count`` requests with ``fault`` instead of a proper reply."""
        self._line_faults.extend([fault] * count)

    # -- serving ---------------------------------------------------------------------------
    def _line(self) -> int:
        """The descriptor requests come in on and answers go out on (-1: no client yet)."""
        if self._listener is None:
            return self._master
        return self._client.fileno() if self._client is not None else -1

    def _accept(self, listener: socket.socket) -> None:
        try:
            conn, _ = listener.accept()
            conn.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)  # a relay sends at once
        except OSError:  # the client gave up before it was accepted
            return
        if self._client is not None:
            self._client.close()
        self._client = conn

    def _serve(self) -> None:
        try:
            self._serve_line()
        finally:
            self._close_line()

    def _serve_line(self) -> None:
        buf = b""
        last_rx = time.monotonic()
        listener = self._listener
        while not self._stop.is_set():
            line = self._line()
            watched = [fd for fd in (line,) if fd >= 0]
            if listener is not None:
                watched.append(listener.fileno())
            ready, _, _ = select.select(watched, [], [], 0.05)
            if not ready:
                if buf and time.monotonic() - last_rx > FRAME_GAP_S:
                    buf = b""
                continue
            if listener is not None and listener.fileno() in ready:
                self._accept(listener)
                buf = b""
                continue
            try:
                data = os.read(line, 512)
            except OSError:
                continue
            if not data and self._client is not None:  # the client closed its connection
                self._client.close()
                self._client, buf = None, b""
                continue
            buf += data
            last_rx = time.monotonic()
            while buf:
                used, pdu = self._framer.handleFrame(buf, self.slave_id, 0)
                buf = buf[used:]
                if pdu is None:
                    break
                self.requests_seen += 1
                self._reply(self._handle(pdu))

    def _handle(self, pdu: ModbusPDU) -> ModbusPDU:
        fc = pdu.function_code
        if fc in (0x03, 0x04):
            regs = self.model.read_registers(pdu.address, pdu.count)
            if regs is None:
                return ExceptionResponse(fc, ILLEGAL_ADDRESS, self.slave_id)
            cls = ReadInputRegistersResponse if fc == 0x04 else ReadHoldingRegistersResponse
            return cls(registers=regs, dev_id=self.slave_id)
        if fc == 0x10:
            offset = pdu.address - ACTION_REQUEST_ADDR
            if offset < 0 or offset + len(pdu.registers) > N_REGISTERS or not pdu.registers:
                return ExceptionResponse(fc, ILLEGAL_ADDRESS, self.slave_id)
            self.model.write_request(offset, list(pdu.registers))
            return WriteMultipleRegistersResponse(
                address=pdu.address, count=len(pdu.registers), dev_id=self.slave_id
            )
        if fc == 0x17:  # read/write multiple registers: the write happens before the read
            assert isinstance(pdu, ReadWriteMultipleRegistersRequest)
            offset = pdu.write_address - ACTION_REQUEST_ADDR
            regs_in = list(pdu.write_registers)
            if offset < 0 or offset + len(regs_in) > N_REGISTERS or not regs_in:
                return ExceptionResponse(fc, ILLEGAL_ADDRESS, self.slave_id)
            if self.model.read_registers(pdu.read_address, pdu.read_count) is None:
                return ExceptionResponse(fc, ILLEGAL_ADDRESS, self.slave_id)
            self.model.write_request(offset, regs_in)
            regs = self.model.read_registers(pdu.read_address, pdu.read_count)
            assert regs is not None
            return ReadWriteMultipleRegistersResponse(registers=regs, dev_id=self.slave_id)
        return ExceptionResponse(fc, ILLEGAL_FUNCTION, self.slave_id)

    def _reply(self, response: ModbusPDU) -> None:
        frame = self._framer.buildFrame(response)
        fault = self._line_faults.pop(0) if self._line_faults else None
        if fault == "no_answer":
            return
        if fault == "late":  # a busy device: it answers in order, this one late, then the rest
            time.sleep(LATE_ANSWER_S)
        if fault == "bad_crc":
            frame = frame[:-1] + bytes([frame[-1] ^ 0x5A])
        elif fault == "garbage":
            frame = bytes((0xA5 ^ (7 * i)) & 0xFF for i in range(len(frame) + 3))
        with contextlib.suppress(OSError):
            if self._client is not None:
                self._client.sendall(frame)
            elif self._listener is None and self._master >= 0:
                os.write(self._master, frame)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        prog="python -m fakes.gripper",
        description="Fake Robotiq 2F-85 on a pseudo-terminal or a TCP relay.")
    where = parser.add_mutually_exclusive_group(required=True)
    where.add_argument("--link", help="symlink to create for the serial device")
    where.add_argument("--tcp", metavar="[HOST:]PORT",
                       help="serve a raw TCP stream instead, as a UR controller relays a tool "
                       "flange's RS-485 (clients open socket://HOST:PORT)")
    parser.add_argument("--slave-id", type=int, default=DEFAULT_SLAVE_ID)
    parser.add_argument("--object-mm", type=float, default=None,
                        help="width of a test piece clamped between the fingers (none by "
                        "default)")
    parser.add_argument("--activation-s", type=float, default=0.5)
    args = parser.parse_args(argv)
    piece = None if args.object_mm is None else BenchPiece(args.object_mm)
    if args.tcp is not None:
        host, _, port = args.tcp.rpartition(":")
        fake = FakeGripper(None, args.slave_id, args.activation_s, piece, transport="tcp",
                           tcp_host=host or "127.0.0.1", tcp_port=int(port)).start()
        where_text = fake.port
    else:
        fake = FakeGripper(args.link, args.slave_id, args.activation_s, piece).start()
        where_text = f"{fake.port} -> {fake._slave_name}"
    stopped = threading.Event()
    signal.signal(signal.SIGTERM, lambda *_: stopped.set())
    print(f"fake gripper ready on {where_text} (slave {fake.slave_id})", flush=True)
    try:
        stopped.wait()
    except KeyboardInterrupt:
        pass
    finally:
        fake.stop()
    return 0


if __name__ == "__main__":
    sys.exit(main())
