"""A small URScript interpreter: the subset of URScript the simulator executes.

Programs arriving on the primary, secondary or real-time ports (30001-30003), custom scripts
from ``ur_rtde``'s ``sendCustomScript``/``sendCustomScriptFunction`` and the dashboard's
program list all run here, except ur_rtde's own control script (see :mod:`.script`).

A program is compiled first, as the real controller does: any statement outside the supported
subset (control flow, variables, an unknown function) rejects the whole program with a
"compile error" text message before anything moves, so a client never waits on a program that
silently does nothing. Supported statements are calls, one per line:

- motion: ``movej``, ``movel``, ``movep`` (run as ``movel``), ``speedj``, ``speedl``,
  ``stopj``, ``stopl``, ``servoj`` (one target, as a short move) -- targets are joint lists or
  ``p[...]`` poses (a pose for ``movej`` goes to its inverse kinematics, a joint list for
  ``movel`` to its forward kinematics);
- I/O and registers: ``set_digital_out``, ``set_standard_digital_out``,
  ``set_configurable_digital_out``, ``set_tool_digital_out``, ``set_analog_out``,
  ``set_standard_analog_out``, ``write_output_integer_register``,
  ``write_output_float_register``, ``write_output_boolean_register``;
- settings: ``set_tcp``, ``set_payload``, ``set_payload_mass``, ``set_payload_cog``,
  ``set_gravity``, ``set_tool_voltage``;
- flow: ``sleep``, ``sync``, ``textmsg``, ``popup``, ``halt``.

Motion statements block until the motion ends, as in URScript; a motion the arm refuses
(unreachable, protective stop) is a runtime error that ends the program with a message.
"""

from __future__ import annotations

import ast
import math
import re
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field

from fakes.ur_controller.registers import RegisterFile
from fakes.ur_sim import EngineError, MotionEngine
from fakes.ur_sim.engine import CommandOutcome

MOVE_TIMEOUT_S = 120.0


class URScriptError(Exception):
    """A program the simulator cannot compile (outside the supported subset)."""


class URScriptRuntimeError(Exception):
    """A statement failed while the program ran."""


@dataclass(frozen=True)
class Pose:
    """A URScript pose literal ``p[x, y, z, rx, ry, rz]``."""

    values: tuple[float, ...]


Value = float | bool | str | Pose | list[float]


@dataclass(frozen=True)
class Call:
    name: str
    args: tuple[Value, ...]
    kwargs: dict[str, Value] = field(default_factory=dict)
    line: int = 0


@dataclass
class Program:
    name: str
    calls: list[Call]
    secondary: bool = False  # "sec" programs run beside the main program and may not move


_HEADER = re.compile(r"^(def|sec)\s+([A-Za-z_]\w*)\s*\(\s*\)\s*:\s*$")
_POSE = re.compile(r"\bp\s*\[")
_MOTION = {"movej", "movel", "movep", "speedj", "speedl", "stopj", "stopl", "servoj"}
_KNOWN = _MOTION | {
    "set_digital_out", "set_standard_digital_out", "set_configurable_digital_out",
    "set_tool_digital_out", "set_analog_out", "set_standard_analog_out",
    "write_output_integer_register", "write_output_float_register",
    "write_output_boolean_register", "set_tcp", "set_payload", "set_payload_mass",
    "set_payload_cog", "set_gravity", "set_tool_voltage", "sleep", "sync", "textmsg", "popup",
    "halt",
}


def _mark_poses(expr: str) -> str:
    """``p[...]`` -> ``_pose([...])`` so that Python's parser reads the expression."""
    out = expr
    while True:
        m = _POSE.search(out)
        if m is None:
            return out
        start = m.end() - 1
        depth = 0
        for i in range(start, len(out)):
            depth += {"[": 1, "]": -1}.get(out[i], 0)
            if depth == 0:
                out = out[:m.start()] + "_pose(" + out[start:i + 1] + ")" + out[i + 1:]
                break
        else:
            raise URScriptError(f"unbalanced brackets in {expr!r}")


def _value(node: ast.expr) -> Value:
    if isinstance(node, ast.Constant) and isinstance(node.value, int | float | bool | str):
        return node.value if isinstance(node.value, bool | str) else float(node.value)
    if isinstance(node, ast.UnaryOp) and isinstance(node.op, ast.USub | ast.UAdd):
        v = _value(node.operand)
        if isinstance(v, float):
            return -v if isinstance(node.op, ast.USub) else v
    if isinstance(node, ast.BinOp) and isinstance(node.op, ast.Add | ast.Sub | ast.Mult | ast.Div):
        a, b = _value(node.left), _value(node.right)
        if isinstance(a, float) and isinstance(b, float):
            ops: dict[type, Callable[[float, float], float]] = {
                ast.Add: lambda x, y: x + y, ast.Sub: lambda x, y: x - y,
                ast.Mult: lambda x, y: x * y, ast.Div: lambda x, y: x / y}
            return ops[type(node.op)](a, b)
    if isinstance(node, ast.List):
        items = [_value(e) for e in node.elts]
        if all(isinstance(i, float) for i in items):
            return [float(i) for i in items]  # type: ignore[arg-type]
    if (isinstance(node, ast.Call) and isinstance(node.func, ast.Name)
            and node.func.id == "_pose" and len(node.args) == 1):
        inner = _value(node.args[0])
        if isinstance(inner, list) and len(inner) == 6:
            return Pose(tuple(inner))
    if isinstance(node, ast.Name) and node.id == "pi":
        return math.pi
    raise URScriptError(f"unsupported expression {ast.unparse(node)!r}")


def parse_statement(text: str, line: int = 0) -> Call:
    try:
        tree = ast.parse(_mark_poses(text.strip()), mode="eval")
    except SyntaxError as err:
        raise URScriptError(f"line {line}: cannot parse {text.strip()!r}") from err
    node = tree.body
    if not (isinstance(node, ast.Call) and isinstance(node.func, ast.Name)):
        raise URScriptError(f"line {line}: only function calls are supported: {text.strip()!r}")
    name = node.func.id
    if name not in _KNOWN:
        raise URScriptError(f"line {line}: {name}() is not supported by the simulator")
    kwargs = {k.arg: _value(k.value) for k in node.keywords if k.arg is not None}
    return Call(name, tuple(_value(a) for a in node.args), kwargs, line)


def compile_program(text: str) -> Program:
    """Compile a program (``def``/``sec`` block or bare statements); URScriptError if any
    line is outside the supported subset."""
    lines = [(i + 1, ln.split("#", 1)[0].rstrip()) for i, ln in enumerate(text.splitlines())]
    lines = [(i, ln) for i, ln in lines if ln.strip()]
    name, secondary = "<unnamed>", False
    if lines:
        m = _HEADER.match(lines[0][1].strip())
        if m is not None:
            if lines[-1][1].strip() != "end":
                raise URScriptError(f"program {m[2]} has no end")
            name, secondary = m[2], m[1] == "sec"
            lines = lines[1:-1]
    calls = [parse_statement(ln, i) for i, ln in lines]
    if secondary and any(c.name in _MOTION for c in calls):
        raise URScriptError("a secondary program may not move the arm")
    return Program(name, calls, secondary)


def split_programs(buffer: str) -> tuple[list[str], str]:
    """Complete programs in a received text stream, and the incomplete rest: ``def``/``sec``
    blocks up to their ``end`` line, or single statements up to their newline."""
    programs: list[str] = []
    while True:
        buffer = buffer.lstrip("\r\n\t ")
        if not buffer:
            return programs, ""
        if re.match(r"(def|sec)\s", buffer):
            m = re.search(r"^end\s*$", buffer, re.MULTILINE)
            if m is None:
                return programs, buffer
            programs.append(buffer[:m.end()])
            buffer = buffer[m.end():]
        else:
            if "\n" not in buffer:
                return programs, buffer
            line, buffer = buffer.split("\n", 1)
            if line.strip() and not line.lstrip().startswith("#"):
                programs.append(line)


def _floats(v: Value, n: int, what: str) -> list[float]:
    vals = list(v.values) if isinstance(v, Pose) else v
    if not (isinstance(vals, list) and len(vals) == n):
        raise URScriptRuntimeError(f"{what} must be {n} numbers")
    return [float(x) for x in vals]


def _num(v: Value, what: str) -> float:
    if isinstance(v, bool) or not isinstance(v, float):
        raise URScriptRuntimeError(f"{what} must be a number")
    return v


PROGRAM_SWITCH_TIMEOUT_S = 3.0  # a 3 rad/s^2 stop from 180 deg/s takes about 1 s


class ScriptRunner:
    """Runs one compiled program on its own thread against the engine and the registers."""

    def __init__(self, program: Program, engine: MotionEngine, regs: RegisterFile,
                 on_message: Callable[[str], None], on_end: Callable[[ScriptRunner], None]
                 ) -> None:
        self.program = program
        self.engine = engine
        self.regs = regs
        self._message = on_message
        self._on_end = on_end
        self._stop = threading.Event()
        self._resume = threading.Event()
        self._resume.set()
        self.error = ""
        self.running = True
        self._thread = threading.Thread(target=self._run, daemon=True,
                                        name=f"urscript-{program.name}")

    def start(self) -> None:
        self._thread.start()

    @property
    def paused(self) -> bool:
        return not self._resume.is_set()

    def stop(self) -> None:
        self._stop.set()
        self._resume.set()
        if threading.current_thread() is not self._thread:
            self._thread.join(timeout=2.0)

    def pause(self) -> None:
        self._resume.clear()
        self.engine.stop_j(3.0)

    def resume(self) -> None:
        self._resume.set()

    def _run(self) -> None:
        try:
            if not self.program.secondary:
                # A main program that replaces a running one starts once the old one has
                # stopped the arm, as a real controller's program passes through STOPPING
                # first: urx's set_tcp (a one-line program) sent during its own movej
                # stops the move and then sets the TCP.
                self.engine.wait_until_idle(PROGRAM_SWITCH_TIMEOUT_S)
            for call in self.program.calls:
                if self._stop.is_set():
                    break
                self._exec(call)
        except (URScriptRuntimeError, EngineError) as exc:
            self.error = str(exc)
            self._message(f"Runtime error in {self.program.name}: {exc}")
        finally:
            self.running = False
            if not self.program.secondary and self.engine.snapshot().active_command in (
                    "speedj", "speedl"):
                self.engine.stop_j(3.0)  # a program that ends leaves no speed command on
            self._on_end(self)

    def _wait_motion(self, cid: int, call: Call) -> None:
        """Block until the motion ends; a pause stops it and re-runs the statement after."""
        deadline = time.monotonic() + MOVE_TIMEOUT_S
        while time.monotonic() < deadline:
            outcome = self.engine.wait_for(cid, 0.05)
            if self._stop.is_set():
                self.engine.stop_j(3.0)
                return
            if self.paused:
                self._resume.wait()
                if not self._stop.is_set():
                    self._exec(call)
                return
            if outcome == CommandOutcome.SUCCEEDED:
                return
            if outcome == CommandOutcome.ABORTED:
                raise URScriptRuntimeError(f"{call.name} aborted: "
                                           f"{self.engine.snapshot().last_stop_reason}")
            if outcome == CommandOutcome.PREEMPTED:
                return
        raise URScriptRuntimeError(f"{call.name} did not finish in {MOVE_TIMEOUT_S:g} s")

    def _sleep(self, seconds: float) -> None:
        end = time.monotonic() + max(0.0, seconds)
        while not self._stop.is_set() and time.monotonic() < end:
            self._stop.wait(min(0.01, end - time.monotonic()))

    def _arg(self, call: Call, i: int, name: str, default: Value | None = None) -> Value:
        if i < len(call.args):
            return call.args[i]
        if name in call.kwargs:
            return call.kwargs[name]
        if default is None:
            raise URScriptRuntimeError(f"{call.name}: missing argument {name}")
        return default

    def _exec(self, call: Call) -> None:
        e, n = self.engine, call.name
        if n in ("movej", "movel", "movep", "servoj"):
            target = self._arg(call, 0, "q")
            linear = n in ("movel", "movep")
            a = _num(self._arg(call, 1, "a", 1.2 if linear else 1.4), "a")
            v = _num(self._arg(call, 2, "v", 0.25 if linear else 1.05), "v")
            if linear:
                pose = (_floats(target, 6, "pose") if isinstance(target, Pose)
                        else e.fk(_floats(target, 6, "q")))
                cid = e.move_l(pose, v, a)
            elif isinstance(target, Pose):
                cid = e.move_j_ik(_floats(target, 6, "pose"), v, a)
            else:
                cid = e.move_j(_floats(target, 6, "q"), v, a)
            self._wait_motion(cid, call)
        elif n in ("speedl", "speedj"):
            xd = _floats(self._arg(call, 0, "xd" if n == "speedl" else "qd"), 6, "speeds")
            a = _num(self._arg(call, 1, "a", 0.5), "a")
            t = _num(call.kwargs.get("t", call.kwargs.get("t_min",
                     call.args[2] if len(call.args) > 2 else 0.0)), "t")
            if n == "speedl":
                e.speed_l(xd, a, 0.0)
            else:
                e.speed_j(xd, a, 0.0)
            self._sleep(t)
        elif n in ("stopl", "stopj"):
            a = _num(self._arg(call, 0, "a", 2.0), "a")
            (e.stop_l if n == "stopl" else e.stop_j)(a)
            e.wait_until_idle(10.0)
        elif n in ("set_digital_out", "set_standard_digital_out", "set_configurable_digital_out",
                   "set_tool_digital_out"):
            self._digital_out(n, call)
        elif n in ("set_analog_out", "set_standard_analog_out"):
            i = int(_num(self._arg(call, 0, "n"), "n"))
            if i not in (0, 1):
                raise URScriptRuntimeError(f"{n}: analog output {i} does not exist")
            with self.regs.lock:
                self.regs.analog_out[i] = _num(self._arg(call, 1, "f"), "f")
        elif n.startswith("write_output_"):
            self._write_register(n, call)
        elif n == "set_tcp":
            e.set_tcp(_floats(self._arg(call, 0, "pose"), 6, "pose"))
        elif n in ("set_payload", "set_payload_mass"):
            with self.regs.lock:
                self.regs.payload_kg = _num(self._arg(call, 0, "m"), "m")
                if n == "set_payload" and (len(call.args) > 1 or "cog" in call.kwargs):
                    cog = _floats(self._arg(call, 1, "cog"), 3, "cog")
                    self.regs.payload_cog_m = (cog[0], cog[1], cog[2])
        elif n == "set_payload_cog":
            cog = _floats(self._arg(call, 0, "cog"), 3, "cog")
            with self.regs.lock:
                self.regs.payload_cog_m = (cog[0], cog[1], cog[2])
        elif n in ("set_gravity", "set_tool_voltage"):
            pass  # accepted: nothing in the simulation depends on them
        elif n == "sleep":
            self._sleep(_num(self._arg(call, 0, "t"), "t"))
        elif n == "sync":
            self._sleep(0.002)
        elif n in ("textmsg", "popup"):
            self._message(" ".join(str(a) for a in call.args))
        elif n == "halt":
            self._stop.set()

    def _digital_out(self, n: str, call: Call) -> None:
        i = int(_num(self._arg(call, 0, "n"), "n"))
        on = bool(self._arg(call, 1, "b"))
        bank = {"set_digital_out": "standard_do", "set_standard_digital_out": "standard_do",
                "set_configurable_digital_out": "configurable_do",
                "set_tool_digital_out": "tool_do"}[n]
        width = 2 if bank == "tool_do" else 8
        if not 0 <= i < width:
            raise URScriptRuntimeError(f"{n}: output {i} does not exist")
        with self.regs.lock:
            word = getattr(self.regs, bank)
            setattr(self.regs, bank, (word | (1 << i)) if on else (word & ~(1 << i)))

    def _write_register(self, n: str, call: Call) -> None:
        i = int(_num(self._arg(call, 0, "address"), "address"))
        value = self._arg(call, 1, "value")
        with self.regs.lock:
            if n == "write_output_integer_register" and 0 <= i < len(self.regs.out_int):
                self.regs.out_int[i] = int(_num(value, "value"))
            elif n == "write_output_float_register" and 0 <= i < len(self.regs.out_double):
                self.regs.out_double[i] = _num(value, "value")
            elif n == "write_output_boolean_register" and 0 <= i < 64:
                bit = 1 << (64 + i)  # RTDE output_bit_register_64..127
                self.regs.out_bits = (self.regs.out_bits | bit) if bool(value) else (
                    self.regs.out_bits & ~bit)
            else:
                raise URScriptRuntimeError(f"{n}: register {i} does not exist")
