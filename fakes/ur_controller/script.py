"""The interpreter of ur_rtde's register mailbox (its control script, uploaded to 30003).

The simulator does not execute URScript. It recognises the control script ur_rtde uploads
(``rtde_control.script``), takes from it the two things the client injects (the register offset
and a move path), and then behaves as that script does, cycle by cycle: it reads the command
id from ``input_int_register_0`` and the arguments from the input registers, drives the motion
engine, reports ready (1) / done (2) in ``output_int_register_0``, results in the output
registers and async progress in ``output_int_register_2``. Runtime errors (an unreachable target,
a refused command) stop the program with a text message, as on the real controller.
"""

from __future__ import annotations

import logging
import os
import re
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from scipy.spatial.transform import Rotation

from fakes.ur_controller.registers import RegisterFile
from fakes.ur_controller.rtde import LEVEL_ERROR
from fakes.ur_sim import EngineError, EngineSnapshot, MotionEngine, RobotMode, SafetyMode
from fakes.ur_sim.engine import CommandOutcome, CommandRejectedError, PathEntry

log = logging.getLogger(__name__)

READY, DONE = 1, 2
RUNTIME_STOPPED, RUNTIME_PLAYING, RUNTIME_PAUSED = 1, 2, 4
CONTROL_SCRIPT_MARK = "RTDE Control Script"
# commands the script treats as real-time: processed every cycle, answered with "ready"
REALTIME_CMDS = {24, 11, 9, 10, 26, 27, 38, 58, 66, 67, 68, 69, 70, 71}
STOP_SCRIPT = 255
# mailbox commands the simulator refuses (see MailboxInterpreter.refuse), by ur_rtde's names
REFUSED_CMDS = {6: "forceMode", 12: "servoC", 25: "toolContact", 28: "getTargetWaypoint"}
REFUSE_RESUME_S = 0.3
# A real controller receives RTDE input whatever its host does; this one shares a host. When
# its own cycle was held up this long, packages written meanwhile may still sit unread in its
# sockets: the watchdog waits WATCHDOG_GRACE_S for them before it judges.
WATCHDOG_STALL_S = 0.02
WATCHDOG_GRACE_S = 0.01
# speedStop, servoStop, stopL, stopJ: their receive times go to the stop log (see StopLog)
STOP_CMDS = {15: "speedStop", 16: "servoStop", 33: "stopL", 34: "stopJ"}
STOP_LOG_ENV = "UR_SIM_STOP_LOG"


class StopLog:
    """Where the controller notes when each stop command arrived: the RTDE receive time of the
    package that carried it (host ``time.monotonic()``, shared by every process on the host),
    one line per stop, appended to the file named by ``$UR_SIM_STOP_LOG`` (nothing without
    it). Benchmarks time a stop to this moment, the moment the controller has it."""

    def __init__(self, path: str | None) -> None:
        self._file = open(path, "a", buffering=1) if path else None  # noqa: SIM115

    def note(self, name: str, received_s: float) -> None:
        if self._file is not None:
            self._file.write(f"{received_s:.6f} {name}\n")
_MOVE = re.compile(
    r"^\s*(movej|movel|movep)\((p?)\[([^\]]*)\],a=([^,]+),v=([^,]+),r=([^)]+)\)\s*$")


class ScriptError(Exception):
    """A program the simulator cannot run (unsupported motion in an injected path, ...)."""


@dataclass
class ControlProgram:
    """What the simulator needs of an uploaded rtde_control script."""

    int_offset: int = 0
    float_offset: int = 0
    path: list[PathEntry] = field(default_factory=list)


def parse_program(text: str) -> ControlProgram | None:
    """The control program's settings, or None when the text is some other program."""
    if CONTROL_SCRIPT_MARK not in text:
        return None
    prog = ControlProgram()
    m = re.search(r"# int register offset\n\s*(\d+)", text)
    prog.int_offset = int(m[1]) if m else 0
    m = re.search(r"# float register offset\n\s*(\d+)", text)
    prog.float_offset = int(m[1]) if m else 0
    start = text.find("# inject move path\n")
    if start >= 0:
        for line in text[start:].splitlines()[1:]:
            if line.strip() == "end":
                break
            if line.strip().startswith("signal_async_progress"):
                continue
            m = _MOVE.match(line)
            if m is None:
                continue
            target = [float(v) for v in m[3].split(",")]
            # movep (constant tool speed through blends) runs as a blended movel here
            kind = ("movej_pose" if m[1] == "movej" and m[2] else "movej" if m[1] == "movej"
                    else "movel" if m[2] else "movel_joints")
            prog.path.append((kind, target, float(m[5]), float(m[4]), float(m[6])))  # type: ignore[arg-type]
    return prog


def _pose_T(pose6: list[float]) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = Rotation.from_rotvec(pose6[3:6]).as_matrix()
    T[:3, 3] = pose6[:3]
    return T


def _T_pose(T: np.ndarray) -> list[float]:
    return [float(v) for v in T[:3, 3]] + [float(v) for v in
                                            Rotation.from_matrix(T[:3, :3]).as_rotvec()]


class MailboxInterpreter:
    """ur_rtde's control script, as a state machine stepped once per controller cycle."""

    def __init__(self, engine: MotionEngine, regs: RegisterFile,
                 on_message: Callable[..., None]) -> None:
        self.engine = engine
        self.regs = regs
        self._message = on_message
        self.running = False
        self.last_error = ""
        self._prog = ControlProgram()
        self._executing = False
        # engine command id a synchronous mailbox command waits for (0: for the arm to rest)
        self._pending_id: int | None = None
        self._async_id: int | None = None  # an async operation whose end must be signalled
        self._async_is_path = False
        self._async_progress = -1
        self._async_wr_count = 0
        self._async_op_id = 0
        self._speed_args: tuple[float, ...] | None = None
        self._watchdog_s: float | None = None  # set_watchdog: max gap between client writes
        self._last_step_s = time.monotonic()
        self._watchdog_grace_until_s = 0.0
        self._resume: tuple[ControlProgram, float] | None = None  # after a refused command
        self.hand_guiding = False  # teach or freedrive mode
        self._ignore: tuple[int, float] | None = None  # (command, write time) refused
        self._contact: dict[str, Any] | None = None  # a moveUntilContact under way
        self.stop_log = StopLog(os.environ.get(STOP_LOG_ENV))

    # -- program lifecycle ---------------------------------------------------------------------
    def start(self, prog: ControlProgram) -> None:
        self._resume = None
        self._contact = None
        self.hand_guiding = False
        snap = self.engine.snapshot()
        if snap.robot_mode != RobotMode.RUNNING or snap.safety_mode != SafetyMode.NORMAL:
            # An error-level RTDE text message to every streaming client: the only place a
            # client that sees "Failed to start control script" can learn why.
            self._message(f"Program not started: the robot is {snap.robot_mode.name} in "
                          f"safety mode {snap.safety_mode.name}, not RUNNING (power on, "
                          "release the brakes and clear safety stops first: dashboard "
                          "'power on', 'brake release')", LEVEL_ERROR)
            self.running = False
            return
        self._prog = prog
        self._executing = False
        self._pending_id = None
        self._async_id = None
        self._speed_args = None
        self._watchdog_s = None
        self.running = True
        self.engine.set_program_running(True)
        self._write_async(-1)
        self._write_int(0, READY)

    def stop(self, reason: str, brake: bool = True) -> None:
        if not self.running:
            return
        self.running = False
        self.engine.set_program_running(False)
        self._pending_id = None
        self._async_id = None
        self._speed_args = None
        if brake:
            self.engine.stop_j(10.0)
        if reason:
            self._message(reason)

    def runtime_error(self, exc: Exception | str) -> None:
        self.last_error = str(exc)
        self.stop(f"Runtime error: {exc}")

    # -- registers -----------------------------------------------------------------------------
    def _int(self, i: int) -> int:
        return self.regs.in_int[i + self._prog.int_offset]

    def _float(self, i: int) -> float:
        return self.regs.in_double[i + self._prog.float_offset]

    def _floats(self, i: int, n: int = 6) -> list[float]:
        o = i + self._prog.float_offset
        return list(self.regs.in_double[o:o + n])

    def _write_int(self, i: int, value: int) -> None:
        self.regs.out_int[i + self._prog.int_offset] = value

    def _write_floats(self, i: int, values: list[float]) -> None:
        o = i + self._prog.float_offset
        self.regs.out_double[o:o + len(values)] = [float(v) for v in values]

    def _write_async(self, value: int) -> None:
        """The script's progress word: op id, change count, running bit and progress."""
        self._async_wr_count = (self._async_wr_count + 1) % 128
        if value == 0:
            self._async_op_id = (self._async_op_id + 1) % 128
        word = self._async_wr_count * 65536 + self._async_op_id * 16777216
        if value >= 0:
            word += min(value, 32767) + 32768
        self._write_int(2, word)

    # -- the cycle -----------------------------------------------------------------------------
    def step(self, snap: EngineSnapshot) -> None:
        now = time.monotonic()
        if now - self._last_step_s > WATCHDOG_STALL_S:  # this process was not scheduled
            self._watchdog_grace_until_s = now + WATCHDOG_GRACE_S
        self._last_step_s = now
        if not self.running:
            if self._resume is not None and time.monotonic() >= self._resume[1]:
                prog, self._resume = self._resume[0], None
                self.start(prog)
            return
        if snap.safety_mode != SafetyMode.NORMAL or snap.robot_mode != RobotMode.RUNNING:
            self.stop(f"Program stopped: {snap.safety_mode.name} / {snap.robot_mode.name}"
                      + (f" ({snap.last_stop_reason})" if snap.last_stop_reason else ""),
                      brake=False)
            return
        with self.regs.lock:
            if self._watchdog_expired():
                self.stop("RTDE input watchdog: input_int_register not updated in time, "
                          "program stopped")
                return
            self._track_async(snap)
            if self._contact is not None:
                self._step_contact(snap)
                return
            if self._pending_id is not None:
                if self._finished(self._pending_id, snap):
                    self._pending_id = None
                    self._write_int(0, DONE)
                return
            cmd = self._int(0)
            if self._ignore is not None:
                written = self.regs.in_int_written_s[self._prog.int_offset]
                if (cmd, written) == self._ignore:
                    cmd = 0  # the refused command, still in the register: not run again
                else:
                    self._ignore = None
            if cmd in STOP_CMDS and not self._executing:
                self.stop_log.note(STOP_CMDS[cmd],
                                   self.regs.in_int_written_s[self._prog.int_offset])
            try:
                if cmd in REALTIME_CMDS:
                    self._process(cmd, snap)
                    self._write_int(0, READY)
                elif cmd == 0:
                    self._executing = False
                    self._write_int(0, READY)
                elif not self._executing:
                    self._executing = True
                    if (self._process(cmd, snap) and self._pending_id is None
                            and self._contact is None):
                        self._write_int(0, DONE)
            except EngineError as exc:
                self.runtime_error(exc)

    def _watchdog_expired(self) -> bool:
        """rtde_set_watchdog(..., "stop"): the client must keep writing the command register."""
        if self._watchdog_s is None or time.monotonic() < self._watchdog_grace_until_s:
            return False
        written = self.regs.in_int_written_s[self._prog.int_offset]
        return time.monotonic() - written > self._watchdog_s

    def _finished(self, command_id: int, snap: EngineSnapshot) -> bool:
        """Has the motion a command started come to an end? Id 0: wait for the arm to rest."""
        if command_id == 0:
            return snap.active_command is None
        return self.engine.outcome(command_id) != CommandOutcome.RUNNING

    def _track_async(self, snap: EngineSnapshot) -> None:
        if self._async_id is None:
            return
        if self._finished(self._async_id, snap):
            self._async_id = None
            self._write_async(-1)
        elif self._async_is_path and snap.async_progress > self._async_progress:
            self._async_progress = snap.async_progress
            self._write_async(snap.async_progress)

    def _begin_async(self, command_id: int, path: bool = False) -> None:
        self._async_id = command_id
        self._async_is_path = path
        self._async_progress = 0
        self._write_async(0)

    def _end_async(self) -> None:
        if self._async_id is not None:
            self._async_id = None
            self._write_async(-1)

    def _process(self, cmd: int, snap: EngineSnapshot) -> bool:
        """Run one command; False when the program ended (stop script, protective stop)."""
        e = self.engine
        if cmd in (1, 2, 3, 4, 45):
            self._end_async()  # stop_async_move: a new move replaces a running async one
            self._speed_args = None
            asynchronous = self._int(1) == 1
            v, a = self._float(6), self._float(7)
            if cmd == 1:
                cid = e.move_j(self._floats(0), v, a)
            elif cmd == 2:
                cid = e.move_j_ik(self._floats(0), v, a)
            elif cmd == 3:
                cid = e.move_l(self._floats(0), v, a)
            elif cmd == 4:
                cid = e.move_l(e.fk(self._floats(0)), v, a)
            else:
                if not self._prog.path:
                    raise CommandRejectedError("move_path: no path was injected")
                cid = e.move_path(list(self._prog.path))
            if asynchronous:
                self._begin_async(cid, path=cmd == 45)
            else:
                self._pending_id = cid
        elif cmd in (9, 10):
            args = (cmd, *self._floats(0, 8))
            if args != self._speed_args or snap.active_command not in ("speedj", "speedl"):
                self._speed_args = args
                if cmd == 9:
                    e.speed_j(self._floats(0), self._float(6), 0.0)
                else:
                    e.speed_l(self._floats(0), self._float(6), 0.0)
        elif cmd == 11:
            e.servo_j(self._floats(0), self._float(8), self._float(9), self._float(10))
        elif cmd == 24:
            e.servo_l(self._floats(0), self._float(8), self._float(9), self._float(10))
        elif cmd in (15, 16):
            self._speed_args = None
            (e.speed_stop if cmd == 15 else e.servo_stop)(self._float(0))
            self._pending_id = 0
        elif cmd in (33, 34):
            self._end_async()
            self._speed_args = None
            decel = self._float(0)
            (e.stop_l if cmd == 33 else e.stop_j)(decel)
            if self._int(1) == 1:
                self._begin_async(0)
            else:
                self._pending_id = 0
        elif cmd == 41:
            speeds = self._floats(0)
            feature = "tool" if round(self._float(6)) == 1 else "base"
            e.jog_start(speeds, feature, self._float(7))  # type: ignore[arg-type]
        elif cmd == 42:
            e.jog_stop(1.2)
            self._pending_id = 0
        elif cmd == 43:
            self._write_floats(0, list(snap.tcp_pose))
        elif cmd == 44:
            self._write_floats(0, self._fk_with_tcp(self._floats(0), self._floats(6)))
        elif cmd == 58:
            self._write_floats(0, self._fk_with_tcp(list(snap.q), [0.0] * 6))
        elif cmd == 46:
            self._write_floats(0, e.ik(self._floats(0)))
        elif cmd == 30:
            self._write_floats(0, e.ik(self._floats(0), self._floats(6)))
        elif cmd in (60, 61):
            q_near = self._floats(6) if cmd == 61 else None
            try:
                e.ik(self._floats(0), q_near)
                self._write_int(1, 1)
            except EngineError:
                self._write_int(1, 0)
        elif cmd == 29:
            e.set_tcp(self._floats(0))
        elif cmd == 40:
            self._write_floats(0, list(snap.tcp_offset))
        elif cmd == 47:
            self._write_int(1, 0 if snap.moving else 1)
        elif cmd == 26:
            self._write_floats(0, [0.002])
        elif cmd == 27:
            self._write_floats(0, list(snap.q))
        elif cmd == 31:
            # protective_stop() halts the program at once: "done" is never signalled
            e.trigger_protective_stop("protective_stop() called by the program")
            self.stop("Protective stop requested by the program", brake=False)
            return False
        elif cmd == 39:
            T = _pose_T(self._floats(0)) @ _pose_T(self._floats(6))
            self._write_floats(0, _T_pose(T))
        elif cmd == 17:
            self.regs.payload_kg = self._float(0)
            self.regs.payload_cog_m = tuple(self._floats(1, 3))  # type: ignore[assignment]
        elif cmd == STOP_SCRIPT:
            self.stop("Received stop script!", brake=True)
            return False
        elif cmd == 35:
            frequency = self._float(0)
            if not frequency > 0:
                raise CommandRejectedError(f"set_watchdog: frequency {frequency} must be > 0")
            self._watchdog_s = 1.0 / frequency
            self.regs.in_int_written_s[self._prog.int_offset] = time.monotonic()
        elif cmd in (8, 20, 21, 7, 55, 56, 57, 59, 62, 63):
            # F/T zeroing, force-mode tuning and stop, external F/T input, gravity, contact
            # detection on/off: accepted; the simulated arm feels no force, so nothing changes
            pass
        elif cmd == 64:
            touching = e.contact_excess_m(snap.tcp_pose) >= -1e-4
            self._write_int(1, 1 if touching else 0)
        elif cmd == 51:
            if not e.contact_planes:
                self.refuse("moveUntilContact: the simulated world has no contact surface "
                            "(configure one: ControllerProcess.set_contact_plane_z)")
                return False
            e.speed_l(self._floats(0), self._float(12), 0.0)
            self._contact = {"stage": "approach"}
        elif cmd in (18, 52):
            self.hand_guiding = True  # teach/freedrive: nobody pushes the simulated arm
        elif cmd in (19, 53):
            self.hand_guiding = False
        elif cmd == 54:
            self._write_int(1, 1 if self.hand_guiding else 0)
        elif cmd == 36:
            self._write_int(1, 1 if e.pose_within_safety_limits(self._floats(0)) else 0)
        elif cmd == 37:
            self._write_int(1, 1 if e.joints_within_safety_limits(self._floats(0)) else 0)
        elif cmd == 38:
            self._write_floats(0, [0.0] * 6)  # joint torques: no dynamics model, zero
        elif cmd in REFUSED_CMDS:
            self.refuse(f"{REFUSED_CMDS[cmd]} is not simulated by this controller simulator")
            return False
        else:
            self.refuse(f"ur_rtde command {cmd} is not simulated by this controller simulator")
            return False
        return True

    def _step_contact(self, snap: EngineSnapshot) -> None:
        """moveUntilContact: speedl until the TCP reaches a contact surface, stopl, then back
        to where the contact was detected (as ur_rtde's script does), then done."""
        e, c = self.engine, self._contact
        assert c is not None
        if c["stage"] == "approach":
            if e.contact_excess_m(snap.tcp_pose) >= 0.0:
                c["pose"] = list(snap.tcp_pose)
                c["stage"] = "braking"
                e.stop_l(3.0)
            elif snap.active_command != "speedl":
                self._contact = None  # ended otherwise (stopped by a stop or a safety stop)
                self._write_int(0, DONE)
        elif c["stage"] == "braking" and snap.active_command is None:
            c["cid"] = e.move_l(c["pose"], 0.05, 1.0)
            c["stage"] = "retract"
        elif c["stage"] == "retract" and e.outcome(int(c["cid"])) != CommandOutcome.RUNNING:
            self._contact = None
            self._write_int(0, DONE)

    def refuse(self, reason: str) -> None:
        """Answer an unsimulated command: the client's call returns False at once (its
        program is seen to stop), and the same control program resumes by itself shortly
        after, registers and all, so the client's next command runs without a re-upload."""
        self.last_error = reason
        prog = self._prog
        self._ignore = (self._int(0), self.regs.in_int_written_s[prog.int_offset])
        self.stop(f"Refused: {reason}", brake=False)
        self._resume = (prog, time.monotonic() + REFUSE_RESUME_S)

    def _fk_with_tcp(self, q: list[float], tcp6: list[float]) -> list[float]:
        """get_forward_kin(q, tcp): the engine's fk uses its own TCP, so swap it for ``tcp6``."""
        T_base_tcp = _pose_T(self.engine.fk(q))
        T_flange_tcp_current = _pose_T(list(self.engine.snapshot().tcp_offset))
        T_base_flange = T_base_tcp @ np.linalg.inv(T_flange_tcp_current)
        return _T_pose(T_base_flange @ _pose_T(tcp6))
