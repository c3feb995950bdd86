"""Robotiq 2F-85-compatible gripper over Modbus RTU (RS-485), via pymodbus' serial client.

pymodbus does the RTU framing and CRC; this module only knows the gripper's register map and
turns what happens on the wire into :mod:`drivers.errors` types. pymodbus reports a bad CRC, line
garbage and silence all as "no response", so every exchange records the raw bytes received
(pymodbus' ``trace_packet`` hook) to tell the three apart: an integrator at a new cell needs to
know whether the cable is dead (timeout) or the wiring/termination/baud rate is wrong (CRC,
garbage).

Register map (Robotiq 2F-85/2F-140 manual, Modbus RTU section; default slave 9, 115200 8N1):

* Action request, written with FC16 at 0x03E8, 3 registers = 6 bytes, big-endian pairs:
  byte 0 = ``rACT`` (bit 0, activate), ``rGTO`` (bit 3, go to ``rPR``), ``rATR`` (bit 4,
  automatic release); bytes 1-2 reserved; byte 3 ``rPR`` position request (0 open ..
  255 closed); byte 4 ``rSP`` speed; byte 5 ``rFR`` force.
* Gripper status, read with FC04 at 0x07D0, 3 registers: byte 0 = ``gACT`` (bit 0), ``gGTO``
  (bit 3), ``gSTA`` (bits 4-5: 0 reset, 1 activating, 3 activated), ``gOBJ`` (bits 6-7:
  0 moving, 1 contact while opening, 2 contact while closing, 3 at request / no object);
  byte 1 reserved; byte 2 = ``gFLT`` (low nibble) and ``kFLT`` (high nibble); byte 3 ``gPR``
  request echo; byte 4 ``gPO`` position; byte 5 ``gCU`` current (x10 mA).
"""

from __future__ import annotations

import threading
import time
from dataclasses import dataclass

from pymodbus.client import ModbusSerialClient
from pymodbus.exceptions import ConnectionException, ModbusException
from pymodbus.framer import FramerRTU
from pymodbus.pdu import ModbusPDU

from drivers.errors import (
    ConnectionLostError,
    DeviceTimeoutError,
    DriverError,
    MotionError,
    NotReadyError,
    ProtocolError,
)
from drivers.gripper import GripperStatus

ACTION_REQUEST_ADDR = 0x03E8
GRIPPER_STATUS_ADDR = 0x07D0
N_REGISTERS = 3
FUNCTION_CODES = {"read_input_registers": 0x04, "write_registers": 0x10}
STALE_ANSWERS = 2  # late answers to earlier requests skipped before an exchange gives up
DEFAULT_SLAVE_ID = 9
DEFAULT_BAUDRATE = 115200

STROKE_MM = 85.0  # 2F-85: opening at rPR/gPO = 0; 255 is fully closed

# Action request byte 0 bits
RACT = 0x01
RGTO = 0x08
RATR = 0x10

# gSTA values
GSTA_RESET = 0
GSTA_ACTIVATING = 1
GSTA_ACTIVATED = 3

# gOBJ values
GOBJ_MOVING = 0
GOBJ_CONTACT_OPENING = 1
GOBJ_CONTACT_CLOSING = 2
GOBJ_AT_REQUEST = 3

# gFLT codes from the manual; 0x05/0x07 are command-order faults, the rest are device faults.
FAULTS: dict[int, str] = {
    0x05: "action delayed: activation must complete first",
    0x07: "activation bit must be set before an action",
    0x08: "maximum operating temperature exceeded",
    0x09: "no communication for at least 1 second",
    0x0A: "under minimum operating voltage",
    0x0B: "automatic release in progress",
    0x0C: "internal fault",
    0x0D: "activation fault: check for obstructions",
    0x0E: "overcurrent triggered",
    0x0F: "automatic release completed",
}


def position_to_mm(pos: int) -> float:
    """0..255 register units -> finger opening in mm (linear over the 85 mm stroke)."""
    return STROKE_MM * (1.0 - pos / 255.0)


def mm_to_position(opening_mm: float) -> int:
    """Finger opening in mm -> the nearest 0..255 position request."""
    return round(255.0 * (1.0 - opening_mm / STROKE_MM))


def pct_to_byte(pct: float) -> int:
    return round(pct / 100.0 * 255.0)


def fault_text(gflt: int) -> str | None:
    if gflt == 0:
        return None
    return f"0x{gflt:02X}: {FAULTS.get(gflt, 'unknown fault')}"


@dataclass(frozen=True)
class RobotiqStatus:
    """The six status bytes, decoded; the register-level truth behind :class:`GripperStatus`."""

    gACT: int
    gGTO: int
    gSTA: int
    gOBJ: int
    gFLT: int
    kFLT: int
    gPR: int
    gPO: int
    gCU: int

    @classmethod
    def from_registers(cls, regs: list[int]) -> RobotiqStatus:
        if len(regs) != N_REGISTERS:
            raise ProtocolError(f"expected {N_REGISTERS} status registers, got {len(regs)}")
        b = [byte for r in regs for byte in ((r >> 8) & 0xFF, r & 0xFF)]
        return cls(
            gACT=b[0] & 0x01, gGTO=(b[0] >> 3) & 0x01, gSTA=(b[0] >> 4) & 0x03,
            gOBJ=(b[0] >> 6) & 0x03, gFLT=b[2] & 0x0F, kFLT=(b[2] >> 4) & 0x0F,
            gPR=b[3], gPO=b[4], gCU=b[5],
        )

    @property
    def activated(self) -> bool:
        return self.gACT == 1 and self.gSTA == GSTA_ACTIVATED

    @property
    def moving(self) -> bool:
        return self.gGTO == 1 and self.gOBJ == GOBJ_MOVING

    def to_status(self) -> GripperStatus:
        return GripperStatus(
            activated=self.activated,
            position_mm=round(position_to_mm(self.gPO), 2),
            object_detected=self.gOBJ in (GOBJ_CONTACT_OPENING, GOBJ_CONTACT_CLOSING),
            moving=self.moving,
            fault=fault_text(self.gFLT),
        )


def action_registers(action: int, position: int = 0, speed: int = 0, force: int = 0) -> list[int]:
    """The three action-request registers (bytes 1 and 2 are reserved and sent as 0)."""
    return [(action & 0xFF) << 8, position & 0xFF, ((speed & 0xFF) << 8) | (force & 0xFF)]


class RobotiqGripper:
    """:class:`drivers.gripper.Gripper` for a Robotiq 2F-85 (or compatible) on a serial port.

    ``retries`` re-sends a request whose answer was missing or corrupt; the action-request
    writes are idempotent, so a retry never doubles a motion.
    """

    def __init__(
        self, port: str, slave_id: int = DEFAULT_SLAVE_ID, baudrate: int = DEFAULT_BAUDRATE,
        timeout_s: float = 0.5, retries: int = 1, *, speed_pct: float = 100.0,
        force_pct: float = 50.0, poll_interval_s: float = 0.02, motion_timeout_s: float = 5.0,
        activation_timeout_s: float = 10.0,
    ) -> None:
        if not 1 <= slave_id <= 247:
            raise ValueError(f"slave_id must be 1..247, got {slave_id}")
        if timeout_s <= 0:
            raise ValueError(f"timeout_s must be positive, got {timeout_s}")
        self.port = port
        self.slave_id = slave_id
        self.baudrate = baudrate
        self.timeout_s = timeout_s
        self.retries = retries
        self.speed_pct = speed_pct
        self.force_pct = force_pct
        self.poll_interval_s = poll_interval_s
        self.motion_timeout_s = motion_timeout_s
        self.activation_timeout_s = activation_timeout_s
        self._client: ModbusSerialClient | None = None
        self._rx = b""
        self._lock = threading.Lock()  # one exchange at a time: the API polls while moves wait
        self._requested: int | None = None  # rPR of the last move (None: none, or halted)

    # -- connection ------------------------------------------------------------------------
    def connect(self) -> None:
        """Open the port and check that a gripper answers at ``slave_id``."""
        if self._client is not None:
            return
        client = ModbusSerialClient(
            self.port, baudrate=self.baudrate, bytesize=8, parity="N", stopbits=1,
            timeout=self.timeout_s, retries=self.retries, trace_packet=self._trace,
        )
        if not client.connect():
            raise ConnectionLostError(f"cannot open serial port {self.port}")
        self._client = client
        try:
            self.read_raw()
        except DriverError:
            self.disconnect()
            raise

    def disconnect(self) -> None:
        client, self._client = self._client, None
        if client is not None:
            client.close()

    def _trace(self, sending: bool, data: bytes) -> bytes:
        if not sending:
            self._rx = bytes(data)  # pymodbus hands over the whole receive buffer each time
        return data

    # -- register access -------------------------------------------------------------------
    def _execute(self, what: str, call: str, *args: object, **kwargs: object) -> list[int]:
        """One request and its answer. An answer of another function code is a late answer
        to an earlier request (one that timed out, or whose retry was answered first): RTU
        frames carry no transaction id, and pymodbus matches only the slave id. The request
        is sent again (pymodbus empties the receive buffer first; every request here is
        idempotent) until its own answer comes, up to ``STALE_ANSWERS`` times."""
        fc = FUNCTION_CODES[call]
        got, stale = fc, b""
        with self._lock:
            for _ in range(STALE_ANSWERS + 1):
                response = self._exchange(what, call, *args, **kwargs)
                got = response.function_code & 0x7F
                if got == fc:
                    break
                stale = self._rx
            else:
                raise ProtocolError(
                    f"the gripper (slave {self.slave_id}) on {self.port} answered {what} "
                    f"{STALE_ANSWERS + 1} times with answers to other requests (function "
                    f"0x{got:02X}, expected 0x{fc:02X}; last {stale[:16].hex(' ')}): answers "
                    "arrive later than timeout_s; raise it, or check the bus for another "
                    "master")
        if response.isError():
            raise ProtocolError(
                f"gripper rejected {what} with Modbus exception code "
                f"{getattr(response, 'exception_code', '?')}"
            )
        return list(response.registers)

    def _exchange(self, what: str, call: str, *args: object, **kwargs: object) -> ModbusPDU:
        client = self._client
        if client is None:
            raise NotReadyError("gripper is not connected: call connect() first")
        self._rx = b""
        try:
            response: ModbusPDU = getattr(client, call)(*args, device_id=self.slave_id,
                                                        **kwargs)
        except ConnectionException as err:
            # Close the port (its descriptor and lock go with it); the client stays, and the
            # next request opens the port again, so a link that comes back is used at once.
            client.close()
            raise ConnectionLostError(
                f"serial port {self.port} failed during {what}; the next request reopens it"
            ) from err
        except ModbusException as err:
            raise self._diagnose(what) from err
        return response

    def _diagnose(self, what: str) -> DriverError:
        """Name the failure from the bytes that did (or did not) come back."""
        rx = self._rx
        where = f"gripper (slave {self.slave_id}) on {self.port}"
        if not rx:
            return DeviceTimeoutError(
                f"no answer from {where} to {what} within {self.timeout_s} s: check power, "
                "RS-485 wiring, slave id and baud rate"
            )
        looks_like_reply = rx[1:2] in (b"\x03", b"\x04", b"\x10", b"\x83", b"\x84", b"\x90")
        if len(rx) >= 4 and rx[0] == self.slave_id and looks_like_reply:
            crc = int.from_bytes(rx[-2:], "big")
            if not FramerRTU.check_CRC(rx[:-2], crc):
                return ProtocolError(
                    f"CRC error in the answer from {where} to {what}: {rx.hex(' ')} "
                    "(noise on the line: check shielding, termination and ground)"
                )
        return ProtocolError(
            f"garbage instead of an answer from {where} to {what}: {rx[:32].hex(' ')} "
            "(check baud rate, parity and that only one master is on the bus)"
        )

    def read_raw(self) -> RobotiqStatus:
        regs = self._execute(
            "status read", "read_input_registers", GRIPPER_STATUS_ADDR, count=N_REGISTERS
        )
        return RobotiqStatus.from_registers(regs)

    def write_action(self, action: int, position: int = 0, speed: int = 0, force: int = 0) -> None:
        self._execute(
            "action request", "write_registers", ACTION_REQUEST_ADDR,
            action_registers(action, position, speed, force),
        )

    # -- Gripper interface -----------------------------------------------------------------
    def status(self) -> GripperStatus:
        return self.read_raw().to_status()

    def activate(self) -> GripperStatus:
        """Activate (reset, then set rACT) and wait until gSTA says activated.

        An already activated gripper is left alone: the reset would open the fingers and drop
        whatever they hold.
        """
        raw = self.read_raw()
        if raw.activated and raw.gFLT == 0:
            return raw.to_status()
        self.write_action(0)
        self.write_action(RACT)
        deadline = time.monotonic() + self.activation_timeout_s
        while True:
            raw = self.read_raw()
            if raw.activated:
                return raw.to_status()
            if raw.gFLT not in (0, 0x05):
                raise NotReadyError(f"gripper activation failed: fault {fault_text(raw.gFLT)}")
            if time.monotonic() > deadline:
                raise DeviceTimeoutError(
                    f"gripper did not finish activating within {self.activation_timeout_s} s"
                )
            time.sleep(self.poll_interval_s)

    def open(self, wait: bool = True) -> GripperStatus:
        return self.move(STROKE_MM, self.speed_pct, self.force_pct, wait)

    def close(self, wait: bool = True) -> GripperStatus:
        return self.move(0.0, self.speed_pct, self.force_pct, wait)

    def move(
        self, position_mm: float, speed_pct: float = 100.0, force_pct: float = 50.0,
        wait: bool = True,
    ) -> GripperStatus:
        """Go to an opening; with ``wait`` return when the fingers stopped (target or object)."""
        if not 0.0 <= position_mm <= STROKE_MM:
            raise ValueError(f"position_mm must be within 0..{STROKE_MM}, got {position_mm}")
        for name, pct in (("speed_pct", speed_pct), ("force_pct", force_pct)):
            if not 0.0 <= pct <= 100.0:
                raise ValueError(f"{name} must be within 0..100, got {pct}")
        raw = self.read_raw()
        if not raw.activated:
            raise NotReadyError("gripper is not activated: run activate first")
        target = mm_to_position(position_mm)
        self.write_action(RACT | RGTO, target, pct_to_byte(speed_pct), pct_to_byte(force_pct))
        self._requested = target
        if not wait:
            return self.status()
        return self.wait_for_motion()

    def wait_for_motion(self, timeout_s: float | None = None) -> GripperStatus:
        """Until the fingers of the last move stopped: at the request, on an object, or halted
        by :meth:`stop` (``gGTO`` 0). MotionError on a fault, DeviceTimeoutError after
        ``timeout_s`` (None: ``motion_timeout_s``)."""
        target = self._requested
        timeout_s = self.motion_timeout_s if timeout_s is None else timeout_s
        deadline = time.monotonic() + timeout_s
        while True:
            raw = self.read_raw()
            if raw.gFLT != 0:
                raise MotionError(f"gripper stopped on fault {fault_text(raw.gFLT)}")
            if raw.gGTO == 0 or target is None:
                return raw.to_status()  # halted: the fingers stay where they are
            # gPR echoes the request once the gripper took it; until then gOBJ is stale.
            if raw.gPR == target and raw.gOBJ != GOBJ_MOVING:
                return raw.to_status()
            if time.monotonic() > deadline:
                raise DeviceTimeoutError(
                    f"gripper did not reach {position_to_mm(target):.1f} mm within "
                    f"{timeout_s} s")
            time.sleep(self.poll_interval_s)

    def stop(self) -> GripperStatus:
        """Halt the fingers where they are: the action request with ``rGTO`` cleared (the
        manual's "stop"), activation kept. A grip already made keeps its object."""
        self.write_action(RACT, self._requested or 0)
        self._requested = None
        return self.status()
