"""The Modbus TCP server for PLCs without OPC UA (pymodbus), configured by ``[modbus]``.

One unit (id 1). Holding registers (the PLC writes): 0 command, 1 command sequence, 2 recipe
number (0: none), 3-4 standoff_mm (float32, big-endian word order; 0.0: the recipe's or the
configured standoff), 5 place number (a pick places at the base-frame pose taught as
``place-<n>``; 0: keeps the part). Input registers (the PLC reads): 0 accepted sequence,
1 state, 2 error number, 3 finished sequence, 4-15 the last pose x, y, z (mm), rx, ry, rz (rad)
as float32, 16 heartbeat (+1 every 100 ms), 17 alarm bits, a pick's 18 part id, 19 parts
seen, 20 grip verdict, 21-22 finger width (float32), and the newest calibration check's 23
verdict, 24-25 and 26-27 its error at the tool (mm, deg; float32), 28 cause. The full map, the
error table and the handshake's timing are in docs/plc.md.

The handshake cannot race: the cell acts only when the sequence register changes, and it acts
inside the write's own request, so when the write's response reaches the PLC the accepted
sequence, state ``busy`` and error 0 are already in the input registers. When the command ends,
state, error number and pose are written, and the finished sequence last, in one step on the
server's loop: a PLC that sees ``finished == its sequence`` reads the result of that command.
A command's end is published only while its sequence is the one accepted last (a stop that
overtakes an approach reports the stop).

Writes come only from ``[modbus] clients`` (empty: any); any other client may write only the
stop command (4) and its sequence, so every panel and PLC on the network can stop the arm.
STOP goes to the cell's stop path from the request's own thread of its own pool, never queued
behind a locate.

A refused request (a read or write past the register map, a function the map does not have,
another unit id, a write from an unlisted client) is answered with its Modbus exception and
logged here once, at WARNING, in one line naming the client and the request; pymodbus' own
loggers stay at WARNING without their frame dumps (``cell.supervision.logs``).
"""

from __future__ import annotations

import asyncio
import contextlib
import contextvars
import ipaddress
import logging
import math
import struct
import threading
import time
from collections.abc import Callable, Sequence
from concurrent.futures import ThreadPoolExecutor
from enum import IntEnum
from typing import Any

from pymodbus.constants import ExcCodes
from pymodbus.datastore import ModbusServerContext
from pymodbus.exceptions import NoSuchIdException
from pymodbus.server import ModbusTcpServer
from pymodbus.server.requesthandler import ServerRequestHandler

from api import remote
from api.plc.loop_thread import LoopThread
from api.remote import RemoteCaller
from cell.calibration.check import CHECK_KIND
from cell.config.schema import ModbusConfig
from cell.errors import CellError
from cell.jobs.store import Job
from cell.results.check import CheckResult
from cell.results.jobs import located_pose
from cell.results.pick import PickResult
from cell.service import Cell
from cell.supervision.logs import drop_library_records, quiet_library_loggers

log = logging.getLogger(__name__)

UNIT_ID = 1
HEARTBEAT_PERIOD_S = 0.1
DRIFT_EVERY = 10  # heartbeats between reads of the drift alarm (a database query)
JOB_POLL_S = 0.01
N_HOLDING = 6
N_INPUT = 29
FC_READ_HOLDING, FC_READ_INPUT = 3, 4
FC_WRITES = (6, 16, 23)
MAX_REFUSALS_REMEMBERED = 256  # distinct refusals logged; then the memory starts again
_PEER: contextvars.ContextVar[str] = contextvars.ContextVar("modbus_peer", default="")


class Command(IntEnum):
    LOCATE = 1
    APPROACH = 2
    HOME = 3
    STOP = 4
    GRIPPER_OPEN = 5
    GRIPPER_CLOSE = 6
    PICK = 7
    CHECK_CALIBRATION = 9


class State(IntEnum):
    IDLE = 0
    BUSY = 1
    DONE_OK = 2
    FAILED = 3


class Hr(IntEnum):
    """Holding register addresses."""

    COMMAND = 0
    SEQUENCE = 1
    RECIPE = 2
    STANDOFF_MM = 3  # and 4
    PLACE = 5  # a pick's place pose: the one taught as place-<n>; 0: none


class Ir(IntEnum):
    """Input register addresses."""

    ACCEPTED_SEQUENCE = 0
    STATE = 1
    ERROR = 2
    FINISHED_SEQUENCE = 3
    POSE = 4  # 4..15: x, y, z (mm), rx, ry, rz (rad), float32 each
    HEARTBEAT = 16
    ALARMS = 17
    PART_ID = 18  # the last pick's part
    PARTS_SEEN = 19  # parts of the layout its locate saw
    GRIP = 20  # GripVerdict
    GRIP_WIDTH_MM = 21  # and 22: float32, where the fingers stopped
    CHECK_VERDICT = 23  # the newest calibration check's CheckVerdict
    CHECK_TCP_ERROR_MM = 24  # and 25: float32, its change at the tool
    CHECK_TCP_ERROR_DEG = 26  # and 27: float32
    CHECK_CAUSE = 28  # CheckCause


class GripVerdict(IntEnum):
    """Input register 20 after a pick."""

    NONE = 0  # no pick ended yet, or it ended before closing
    HELD = 1
    MISSED = 2
    OUT_OF_WINDOW = 3


class CheckVerdict(IntEnum):
    """Input register 23."""

    NONE = 0  # no check yet, or the last one ended (or was refused) without a verdict
    OK = 1
    DRIFTED = 2


class CheckCause(IntEnum):
    """Input register 28: what explains a check's figures better."""

    NONE = 0
    CAMERA = 1  # the camera's mount or lens changed
    REFERENCE = 2  # the reference plate moved


class Alarm(IntEnum):
    """Bits of input register 17."""

    PROTECTIVE_STOP = 0
    EMERGENCY_STOP = 1
    CAMERA_DISCONNECTED = 2
    ARM_DISCONNECTED = 3
    GRIPPER_FAULT = 4
    JOB_FAILED = 5  # the last command failed (cleared by the next accepted one)
    CALIBRATION_DRIFT = 6  # a calibration_drift alarm is not acknowledged


# The error numbers of input register 2, one per cell error code a PLC can meet; codes not
# listed fall back to their class (the HTTP status family). Documented in docs/plc.md.
ERROR_NUMBERS: dict[str, int] = {
    "unknown_command": 1, "invalid_request": 2, "invalid_standoff": 2, "busy": 3,
    "recipe_not_found": 4, "recipe_target_not_found": 4, "taught_not_found": 5,
    "target_not_visible": 6, "too_few_blobs": 6, "no_correspondence": 6,
    "estimation_failed": 6, "not_converged": 6, "degenerate_geometry": 6,
    "target_behind_camera": 6, "no_tool_plate": 6, "stale_pose": 7, "camera_lost": 8,
    "camera_stalled": 8,
    "camera_stale": 8, "protective_stop": 9, "emergency_stop": 10, "arm_not_ready": 11,
    "arm_disconnected": 11, "cancelled": 12, "motion_failed": 13, "motion_timeout": 13,
    "controller_watchdog": 13,
    "outside_envelope": 14, "tilt_limit": 14, "move_too_far": 14, "unreachable": 14,
    "speed_limit": 15, "accel_limit": 15, "gripper_unavailable": 16, "forbidden": 17,
    "not_supported": 18,
    "target_lost": 19, "pose_jump": 19, "recipe_store_unreadable": 20,
    "recipe_store_write_failed": 20, "not_ready": 21, "recipe_prepared": 22,
    "recipe_number_taken": 23, "invalid_recipe": 24, "unauthorized": 17,
    "result_not_found": 25, "grasp_missed": 26, "grip_out_of_window": 27, "gripper_fault": 28,
    "taught_wrong_frame": 30,
    "no_reference": 31, "calibration_drift": 32, "too_few_views": 33,
    "dataset_unwritable": 34, "storage_failed": 35, "tracking_lag": 36,
    "internal_error": 99,
}
ERROR_BY_KIND: dict[str, int] = {"invalid": 90, "conflict": 91, "unavailable": 92,
                                 "not_found": 93, "forbidden": 17}
UNKNOWN_ERROR = 99


def error_number(code: str, kind: str = "") -> int:
    return ERROR_NUMBERS.get(code, ERROR_BY_KIND.get(kind, UNKNOWN_ERROR))


def float_words(value: float) -> list[int]:
    """A float32 as two registers, high word first (big-endian, as most PLCs expect)."""
    hi, lo = struct.unpack(">HH", struct.pack(">f", value))
    return [hi, lo]


def words_float(hi: int, lo: int) -> float:
    return float(struct.unpack(">f", struct.pack(">HH", hi, lo))[0])


class _Outcome:
    """What one command ended with, for the input registers."""

    def __init__(self, ok: bool, error: int = 0, pose: list[float] | None = None,
                 pick: tuple[int, int, int, float] | None = None,
                 check: _Check | None = None) -> None:
        self.ok = ok
        self.error = error
        self.pose = pose
        self.pick = pick  # part id, parts seen, grip verdict, finger width (mm)
        self.check = check


class _Check:
    """A calibration check for registers 23-28; ``at_s``: when it ended (UNIX time), so an
    older check never overwrites a newer one."""

    def __init__(self, at_s: float, result: CheckResult | None = None) -> None:
        self.at_s = at_s
        self.verdict = CheckVerdict.NONE if result is None else \
            CheckVerdict.DRIFTED if result.verdict == "drifted" else CheckVerdict.OK
        self.cause = CheckCause.NONE if result is None else \
            CheckCause.REFERENCE if result.cause == "reference" else CheckCause.CAMERA
        self.tcp_error_mm = math.nan if result is None else result.tcp_error_mm
        self.tcp_error_deg = math.nan if result is None else result.tcp_error_deg

    @staticmethod
    def of(job: Job) -> _Check:
        result = job.result if isinstance(job.result, CheckResult) else None
        return _Check(job.ended_at or time.time(), result)


class _Registers(ModbusServerContext):
    """The one unit's registers. pymodbus calls these from its loop for every request; the
    cell's answers land here through ``loop.call_soon_threadsafe``, so every change is one
    step of that loop and a read never sees half of one."""

    def __init__(self, server: ModbusServer) -> None:  # no devices: this is the datastore
        self.old_simulator = True  # pymodbus then calls these methods directly
        self.simdevices = []
        self._devices = {}
        self.server = server
        self.holding = [0] * N_HOLDING
        self.input = [0] * N_INPUT

    def device_ids(self) -> list[int]:
        return [UNIT_ID]

    def _unit(self, device_id: int, func_code: int) -> None:
        if device_id != UNIT_ID:
            self.server.refused(f"function {func_code} for unit {device_id}",
                                f"this cell is unit {UNIT_ID} (gateway target failed to respond)")
            raise NoSuchIdException(f"unit {device_id}: this cell is unit {UNIT_ID}")

    async def async_getValues(self, device_id: int, func_code: int, address: int,
                              count: int = 1) -> list[int] | list[bool] | ExcCodes:
        self._unit(device_id, func_code)
        table = self.input if func_code == FC_READ_INPUT else self.holding
        if func_code not in (FC_READ_INPUT, FC_READ_HOLDING, *FC_WRITES):
            self.server.refused(f"function {func_code}", "the map has no such function "
                                "(illegal function)")
            return ExcCodes.ILLEGAL_FUNCTION
        if address < 0 or count < 1 or address + count > len(table):
            what = "input" if func_code == FC_READ_INPUT else "holding"
            self.server.refused(
                f"read of {what} registers {_span(address, count)}",
                f"past the register map, which has {what} registers 0-{len(table) - 1} "
                "(illegal data address)")
            return ExcCodes.ILLEGAL_ADDRESS
        return list(table[address:address + count])

    async def async_setValues(self, device_id: int, func_code: int, address: int,
                              values: Sequence[int] | Sequence[bool]) -> ExcCodes | None:
        self._unit(device_id, func_code)
        if func_code not in FC_WRITES:
            self.server.refused(f"write with function {func_code}", "the map has no such "
                                "function (illegal function)")
            return ExcCodes.ILLEGAL_FUNCTION
        if address < 0 or address + len(values) > N_HOLDING:
            self.server.refused(
                f"write of holding registers {_span(address, len(values))}",
                f"past the register map, which has holding registers 0-{N_HOLDING - 1} "
                "(illegal data address)")
            return ExcCodes.ILLEGAL_ADDRESS
        after = list(self.holding)
        after[address:address + len(values)] = [int(v) for v in values]
        if not self.server.may_write(_PEER.get(), after):
            self.server.refused(f"write of command {after[Hr.COMMAND]}",
                                "a client not in [modbus] clients may write only the stop "
                                "command (illegal function)")
            return ExcCodes.ILLEGAL_FUNCTION
        changed = after[Hr.SEQUENCE] != self.holding[Hr.SEQUENCE]
        self.holding = after
        if changed:
            self.server.accept(after)
        return None


def _span(address: int, count: int) -> str:
    return str(address) if count == 1 else f"{address}-{address + count - 1}"


def _pymodbus_said_refusal(record: logging.LogRecord) -> bool:
    """pymodbus' ERROR line about another unit id: the server has logged it already."""
    return "requested device id does not exist" in str(record.msg)


class _Handler(ServerRequestHandler):
    """Tells the datastore which client is asking (writes are allowed per address)."""

    async def handle_request(self) -> None:
        peer = ""
        with contextlib.suppress(Exception):
            peer = str(self.transport.get_extra_info("peername")[0])
        _PEER.set(peer)
        await super().handle_request()


class _Server(ModbusTcpServer):
    def callback_new_connection(self) -> _Handler:
        return _Handler(self, self.trace_packet, self.trace_pdu, self.trace_connect)


class ModbusServer(LoopThread):
    """``start()`` listens (OSError when the port is taken), ``close()``."""

    thread_name = "modbus"
    what = "the Modbus server"

    def __init__(self, cell: Cell, config: ModbusConfig,
                 on_stop_sent: Callable[[float], None] | None = None) -> None:
        super().__init__()
        self.cell = cell
        self.config = config
        self.caller = RemoteCaller("modbus", "plc", config.role)
        self.allowed = [ipaddress.ip_network(c, strict=False) for c in config.clients]
        self.on_stop_sent = on_stop_sent  # told time.perf_counter() when a STOP is accepted
        self._server: _Server | None = None
        self._closing = threading.Event()
        self._registers: _Registers | None = None
        self._accepted_seq = -1
        self._commands = ThreadPoolExecutor(2, thread_name_prefix="modbus-cmd")
        self._stops = ThreadPoolExecutor(1, thread_name_prefix="modbus-stop")
        self._refusals: set[tuple[str, str]] = set()  # (client, request) already logged
        self._check_at_s = -math.inf  # when the check registers 23-28 show ended
        self._drift_alarm = False  # refreshed every DRIFT_EVERY heartbeats

    @property
    def port(self) -> int:
        if self._server is not None and self._server.transport is not None:
            with contextlib.suppress(Exception):
                sock = self._server.transport.get_extra_info("socket")
                return int(sock.getsockname()[1])
        return self.config.port

    @property
    def registers(self) -> _Registers:
        assert self._registers is not None
        return self._registers

    def start(self, timeout_s: float = 10.0) -> None:
        quiet_library_loggers()
        drop_library_records("pymodbus.logging", _pymodbus_said_refusal)
        super().start(timeout_s)

    def refused(self, request: str, why: str) -> None:
        """One WARNING line for a refused request, the first time this client sends it (a PLC
        polling a wrong address does not fill the log)."""
        peer = _PEER.get() or "a client"
        key = (peer, request)
        if key in self._refusals:
            return
        if len(self._refusals) >= MAX_REFUSALS_REMEMBERED:
            self._refusals.clear()
        self._refusals.add(key)
        log.warning("Modbus %s from %s refused: %s", request, peer, why)

    def close(self) -> None:
        self._closing.set()
        loop, server = self._loop, self._server
        if loop is not None and server is not None and not loop.is_closed():
            with contextlib.suppress(RuntimeError):
                asyncio.run_coroutine_threadsafe(server.shutdown(), loop).result(timeout=5.0)
        self._join(5.0)
        self._commands.shutdown(wait=False, cancel_futures=True)
        self._stops.shutdown(wait=False, cancel_futures=True)

    # -- the server's thread --------------------------------------------------------------------
    async def _main(self) -> None:
        self._loop = asyncio.get_running_loop()
        self._registers = _Registers(self)
        self._server = _Server(self._registers, address=(self.config.host, self.config.port))
        await self._server.listen()
        found = remote.last_check(self.cell)
        if found is not None:
            self._show_check(_Check.of(found[0]))
        self._ready.set()
        threading.Thread(target=self._watch_checks, name="modbus-checks", daemon=True).start()
        ticker = asyncio.create_task(self._heartbeat())
        try:
            await self._server.serving
        finally:
            ticker.cancel()

    def _watch_checks(self) -> None:
        """Registers 23-28 follow every check that ends, whoever ran it (the schedule, HTTP,
        OPC UA): read back from the job store, shown on the server's loop."""
        with self.cell.events.subscribe() as sub:
            while not self._closing.is_set():
                event = sub.get(timeout_s=0.5)
                job = (event or {}).get("job") or {}
                if (event or {}).get("type") != "job" or job.get("kind") != CHECK_KIND \
                        or not job.get("ended_at"):
                    continue
                record = self.cell.jobs.get(str(job.get("id", "")))
                loop = self._loop
                if record is not None and loop is not None and not loop.is_closed():
                    with contextlib.suppress(RuntimeError):
                        loop.call_soon_threadsafe(self._show_check, _Check.of(record))

    def _show_check(self, check: _Check) -> None:
        """Registers 23-28 (on the server's loop): a check newer than the one shown."""
        if check.at_s < self._check_at_s:
            return
        self._check_at_s = check.at_s
        regs = self.registers
        regs.input[Ir.CHECK_VERDICT] = check.verdict
        regs.input[Ir.CHECK_TCP_ERROR_MM:Ir.CHECK_TCP_ERROR_MM + 2] = float_words(
            check.tcp_error_mm)
        regs.input[Ir.CHECK_TCP_ERROR_DEG:Ir.CHECK_TCP_ERROR_DEG + 2] = float_words(
            check.tcp_error_deg)
        regs.input[Ir.CHECK_CAUSE] = check.cause

    async def _heartbeat(self) -> None:
        """Input register 16 counts every 100 ms; the alarm bits follow the cell."""
        while True:
            regs = self.registers
            regs.input[Ir.HEARTBEAT] = (regs.input[Ir.HEARTBEAT] + 1) & 0xFFFF
            if regs.input[Ir.HEARTBEAT] % DRIFT_EVERY == 0:
                self._drift_alarm = self.cell.alarms.active_drift() is not None
            try:
                regs.input[Ir.ALARMS] = self._alarm_bits(regs.input[Ir.ALARMS])
            except Exception:
                log.exception("Modbus alarm update failed")
            await asyncio.sleep(HEARTBEAT_PERIOD_S)

    def _alarm_bits(self, previous: int) -> int:
        st = self.cell.status()
        health = self.cell.health()
        robot = st.get("robot", {})
        bits = previous & (1 << Alarm.JOB_FAILED)
        missing = health.get("missing", [])
        if robot.get("protective_stop"):
            bits |= 1 << Alarm.PROTECTIVE_STOP
        if "EMERGENCY_STOP" in str(robot.get("safety", "")):
            bits |= 1 << Alarm.EMERGENCY_STOP
        if "camera" in missing or not st.get("camera", {}).get("connected", True):
            bits |= 1 << Alarm.CAMERA_DISCONNECTED
        if "arm" in missing or "robot" in missing:
            bits |= 1 << Alarm.ARM_DISCONNECTED
        gripper = st.get("gripper") or {}
        if isinstance(gripper, dict) and gripper.get("error"):
            bits |= 1 << Alarm.GRIPPER_FAULT
        if self._drift_alarm:
            bits |= 1 << Alarm.CALIBRATION_DRIFT
        return bits

    # -- the handshake (on the server's loop) ---------------------------------------------------
    def may_write(self, peer: str, after: list[int]) -> bool:
        """Listed clients write anything; the others only the stop command."""
        if not self.allowed or self._listed(peer):
            return True
        return after[Hr.COMMAND] == Command.STOP

    def _listed(self, peer: str) -> bool:
        try:
            address = ipaddress.ip_address(peer)
        except ValueError:
            return False
        return any(address in net for net in self.allowed)

    def accept(self, holding: list[int]) -> None:
        """A new sequence: accepted now (still inside the write's request), run off the loop."""
        regs = self.registers
        seq, command = holding[Hr.SEQUENCE], holding[Hr.COMMAND]
        self._accepted_seq = seq
        regs.input[Ir.ACCEPTED_SEQUENCE] = seq
        regs.input[Ir.STATE] = State.BUSY
        regs.input[Ir.ERROR] = 0
        regs.input[Ir.ALARMS] &= ~(1 << Alarm.JOB_FAILED)
        if command == Command.STOP:
            if self.on_stop_sent is not None:
                self.on_stop_sent(time.perf_counter())
            self._stops.submit(self._execute, seq, holding)
        else:
            self._commands.submit(self._execute, seq, holding)

    def _finish(self, seq: int, outcome: _Outcome) -> None:
        """State, error, pose, then the finished sequence: one step of the loop."""
        if seq != self._accepted_seq:
            return  # a newer command was accepted meanwhile; it reports instead
        regs = self.registers
        if outcome.pose is not None:
            for i, v in enumerate(outcome.pose):
                regs.input[Ir.POSE + 2 * i:Ir.POSE + 2 * i + 2] = float_words(v)
        if outcome.pick is not None:
            part_id, seen, verdict, width_mm = outcome.pick
            regs.input[Ir.PART_ID] = part_id & 0xFFFF
            regs.input[Ir.PARTS_SEEN] = seen & 0xFFFF
            regs.input[Ir.GRIP] = verdict
            regs.input[Ir.GRIP_WIDTH_MM:Ir.GRIP_WIDTH_MM + 2] = float_words(width_mm)
        if outcome.check is not None:
            self._show_check(outcome.check)
        regs.input[Ir.STATE] = State.DONE_OK if outcome.ok else State.FAILED
        regs.input[Ir.ERROR] = outcome.error
        if not outcome.ok:
            regs.input[Ir.ALARMS] |= 1 << Alarm.JOB_FAILED
        regs.input[Ir.FINISHED_SEQUENCE] = seq

    # -- commands (worker threads) --------------------------------------------------------------
    def _execute(self, seq: int, holding: list[int]) -> None:
        try:
            outcome = self._command(holding)
        except CellError as err:
            outcome = _Outcome(False, error_number(err.code, err.kind))
        except Exception:
            log.exception("Modbus command %s failed", holding[Hr.COMMAND])
            outcome = _Outcome(False, UNKNOWN_ERROR)
        loop = self._loop
        if loop is not None and not loop.is_closed():
            with contextlib.suppress(RuntimeError):
                loop.call_soon_threadsafe(self._finish, seq, outcome)

    def _command(self, holding: list[int]) -> _Outcome:
        command, recipe = holding[Hr.COMMAND], holding[Hr.RECIPE]
        standoff = words_float(holding[Hr.STANDOFF_MM], holding[Hr.STANDOFF_MM + 1])
        if command == Command.STOP:
            out = remote.stop(self.cell, self.caller)
            if not out.get("stopped"):  # the arm, or a moving gripper, did not take it
                return _Outcome(False, error_number("motion_failed"))
            return _Outcome(True)
        if command == Command.LOCATE:
            if recipe:
                remote.require(self.cell, self.caller, "locate", "locate", {"recipe": recipe})
                with remote.recipe_selected(self.cell, recipe):
                    loc = remote.locate(self.cell, self.caller)
            else:
                loc = remote.locate(self.cell, self.caller)
            return _Outcome(True, pose=self._pose(loc.T_base_target))
        if command == Command.APPROACH:
            if not math.isfinite(standoff) or standoff < 0:
                return _Outcome(False, error_number("invalid_standoff"))
            if recipe:
                job = remote.approach_recipe(self.cell, self.caller, recipe,
                                             standoff_mm=standoff or None)
            else:
                job = remote.approach(self.cell, self.caller,
                                      standoff or self.cell.config.approach.standoff_mm, "")
            return self._job_outcome(job)
        if command == Command.HOME:
            return self._job_outcome(remote.home(self.cell, self.caller))
        if command == Command.PICK:
            place = holding[Hr.PLACE]
            try:
                job = remote.pick(self.cell, self.caller, recipe or "", "",
                                  f"place-{place}" if place else "")
            except CellError as err:  # refused before a part was chosen: no part, no grip
                return _Outcome(False, error_number(err.code, err.kind),
                                pick=(0, 0, GripVerdict.NONE, math.nan))
            return self._pick_outcome(self._job_outcome(job), job.id)
        if command == Command.CHECK_CALIBRATION:
            try:
                job = remote.check_calibration(self.cell, self.caller)
            except CellError as err:  # refused (no reference, busy): no verdict
                return _Outcome(False, error_number(err.code, err.kind),
                                check=_Check(time.time()))
            outcome = self._job_outcome(job)
            outcome.check = _Check.of(self.cell.job(job.id))
            return outcome
        if command in (Command.GRIPPER_OPEN, Command.GRIPPER_CLOSE):
            action = "open" if command == Command.GRIPPER_OPEN else "close"
            remote.gripper(self.cell, self.caller, action, None)
            return _Outcome(True)
        return _Outcome(False, error_number("unknown_command"))

    def _job_outcome(self, job: Job) -> _Outcome:
        """Wait for the job's end; an approach reports the pose it located."""
        while not job.finished and not self._closing.is_set():
            time.sleep(JOB_POLL_S)
            job = self.cell.job(job.id)
        if not job.finished:
            return _Outcome(False, error_number("cancelled"))
        if job.state != "succeeded":
            return _Outcome(False, error_number(job.error_code or "internal_error"))
        target = located_pose(job.result)
        if target is None:
            return _Outcome(True)
        return _Outcome(True, pose=[*target.position_mm, *target.rotvec_rad])

    def _pick_outcome(self, outcome: _Outcome, job_id: str) -> _Outcome:
        """A pick's registers: the part and the grip from its result; a pick that failed on
        its grip says which way, and names the part it had chosen (from its progress; 0 and
        0 when it ended before choosing one)."""
        job = self.cell.job(job_id)
        result = job.result
        if isinstance(result, PickResult):
            verdict = {"held": GripVerdict.HELD, "missed": GripVerdict.MISSED,
                       "out_of_window": GripVerdict.OUT_OF_WINDOW}[result.grip.verdict]
            outcome.pick = (result.part.id, result.part.parts_seen, verdict,
                            result.grip.width_mm)
        else:
            verdict = {"grasp_missed": GripVerdict.MISSED,
                       "grip_out_of_window": GripVerdict.OUT_OF_WINDOW}.get(
                           job.error_code or "", GripVerdict.NONE)
            part = (job.progress or {}).get("part") or {}
            outcome.pick = (int(part.get("id", 0)), int(part.get("parts_seen", 0)), verdict,
                            math.nan)
        return outcome

    @staticmethod
    def _pose(T_base: Any) -> list[float]:
        position_mm, rotvec_rad = remote.pose_mm_rad(T_base)
        return position_mm + rotvec_rad
