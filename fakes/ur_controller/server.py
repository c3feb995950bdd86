"""One simulated UR e-Series controller on one host address: RTDE, script port and dashboard
around one :class:`~fakes.ur_sim.MotionEngine`.

The ports are fixed by the client (29999, 30003, 30004), so parallel controllers use different
loopback addresses (127.0.0.2, 127.0.0.3, ...). Every 500 Hz cycle of the engine's controller
clock does what the real controller's cycle does: steps the arm, runs the control program one
step, samples the arm, and sends each RTDE connection its data package when its period is due
(by controller time, so a host stall is caught up with one package per missed cycle).
"""

from __future__ import annotations

import logging
import threading

from fakes.ur_controller.client_interfaces import ClientInterfaces
from fakes.ur_controller.dashboard import dashboard_service
from fakes.ur_controller.faults import Faults
from fakes.ur_controller.registers import ControllerView, RegisterFile
from fakes.ur_controller.rtde import LEVEL_ERROR, LEVEL_INFO, RTDEServer
from fakes.ur_controller.script import (
    RUNTIME_PAUSED,
    RUNTIME_PLAYING,
    RUNTIME_STOPPED,
    ControlProgram,
    MailboxInterpreter,
    ScriptError,
    parse_program,
)
from fakes.ur_controller.urscript import Program, ScriptRunner, URScriptError, compile_program
from fakes.ur_sim import EngineError, MotionEngine, RobotMode, SafetyMode

log = logging.getLogger(__name__)

CONTROLLER_VERSION = (5, 11, 1, 108318)  # >= 5.11: ur_rtde streams at 500 Hz
CYCLE_S = 0.002
IDLE_CYCLE_S = 0.02  # nobody streams: the program still steps, just less often
# A real controller takes tens of milliseconds to compile and start an uploaded program. The
# delay matters: ur_rtde stops its script, clears the command register over RTDE and uploads
# a new script over another socket; a program started at once could still read the stop
# command and end (seen as a rare hang of movePath waiting for the program to run).
PROGRAM_START_S = 0.08
PROGRAM_DIR = "/programs"
# The simulated controller's program folder, for the dashboard's load/play/pause/stop.
DEFAULT_PROGRAMS = {
    f"{PROGRAM_DIR}/home.urp":
        "def home():\n  movej([0.0, -1.571, 1.571, -1.571, -1.571, 0.0], a=1.4, v=1.05)\nend\n",
    f"{PROGRAM_DIR}/wiggle.urp":
        "def wiggle():\n  movej([0.3, -1.571, 1.571, -1.571, -1.571, 0.0], a=1.0, v=0.5)\n"
        "  movej([0.0, -1.571, 1.571, -1.571, -1.571, 0.0], a=1.0, v=0.5)\nend\n",
    f"{PROGRAM_DIR}/io_test.urp":
        "def io_test():\n  set_digital_out(0, True)\n  sleep(0.5)\n"
        "  set_digital_out(0, False)\nend\n",
}


class URController:
    """A simulated controller serving ``host``. Use as a context manager or call close()."""

    def __init__(
        self, host: str = "127.0.0.2", engine: MotionEngine | None = None, *,
        remote_control: bool = True, serial_number: str = "20235500042",
        rtde_port: int = 30004, script_port: int = 30003, dashboard_port: int = 29999,
        primary_port: int = 30001, secondary_port: int = 30002,
        programs: dict[str, str] | None = None,
    ) -> None:
        self.host = host
        self._owns_engine = engine is None  # a caller's engine is the caller's to close
        self.engine = engine if engine is not None else MotionEngine()
        self.remote_control = remote_control
        self.serial_number = serial_number
        self.polyscope_version = ".".join(map(str, CONTROLLER_VERSION))
        self.regs = RegisterFile()
        self.messages: list[str] = []  # every text message the controller emitted
        self._lock = threading.RLock()
        self.interpreter = MailboxInterpreter(self.engine, self.regs, self._message)
        self._starting: tuple[ControlProgram, float] | None = None  # uploaded, not yet running
        self._runner: ScriptRunner | None = None  # a URScript program (not ur_rtde's)
        self.programs = dict(programs if programs is not None else DEFAULT_PROGRAMS)
        self._loaded: str | None = None
        self.rtde = RTDEServer(host, self.regs, CONTROLLER_VERSION, self._apply_io, rtde_port)
        self.client_interfaces = ClientInterfaces(
            host, self._on_program, CONTROLLER_VERSION,
            (primary_port, secondary_port, script_port))
        self.script = self.client_interfaces.services["realtime"]
        self.dashboard = dashboard_service(host, self, dashboard_port)
        self.faults = Faults(
            {"rtde": self.rtde.service, "script": self.script, "dashboard": self.dashboard,
             "primary": self.client_interfaces.services["primary"],
             "secondary": self.client_interfaces.services["secondary"]},
            self.engine, lambda: self.close(reset=True))
        self._alive = True
        self._t0_host = self.engine.snapshot().host_monotonic_s - self.engine.controller_time_s()
        self.engine.set_cycle_hook(self._cycle_once, self._wants_cycles, IDLE_CYCLE_S)

    # -- program ------------------------------------------------------------------------------
    def program_state(self) -> str:
        runner = self._runner
        if runner is not None and runner.running:
            return "PAUSED" if runner.paused else "PLAYING"
        return "PLAYING" if self.interpreter.running else "STOPPED"

    def program_name(self) -> str:
        if self.interpreter.running:
            return "rtde_control"
        if self._loaded is not None:
            return self._loaded.rsplit("/", 1)[-1]
        runner = self._runner
        return runner.program.name if runner is not None else "<unnamed>"

    def runtime_state(self) -> int:
        state = self.program_state()
        return {"PLAYING": RUNTIME_PLAYING, "PAUSED": RUNTIME_PAUSED}.get(state, RUNTIME_STOPPED)

    def stop_program(self, reason: str) -> None:
        with self._lock:
            self._starting = None
            self.interpreter.stop(reason)
            self._stop_runner()

    # -- the dashboard's program list ----------------------------------------------------------
    def loaded_program(self) -> str | None:
        return self._loaded

    def load_program(self, name: str) -> bool:
        path = name.strip()
        path = path if path.startswith("/") else f"{PROGRAM_DIR}/{path}"
        if path not in self.programs:
            return False
        with self._lock:
            self._loaded = path
        return True

    def play(self) -> bool:
        """Dashboard ``play``: run (or resume) the loaded program; False when refused."""
        with self._lock:
            runner = self._runner
            if runner is not None and runner.running and runner.paused:
                runner.resume()
                return True
            snap = self.engine.snapshot()
            if (self._loaded is None or snap.robot_mode != RobotMode.RUNNING
                    or snap.safety_mode != SafetyMode.NORMAL):
                return False
            try:
                program = compile_program(self.programs[self._loaded])
            except URScriptError as exc:
                self._message(f"Compile error in {self._loaded}: {exc}", LEVEL_ERROR)
                return False
            self.interpreter.stop("", brake=False)
            self._starting = None
            self._start_runner(program)
            return True

    def pause(self) -> bool:
        runner = self._runner
        if runner is None or not runner.running or runner.paused:
            return False
        runner.pause()
        return True

    # -- programs arriving on 30001-30003 ----------------------------------------------------
    def _on_program(self, text: str) -> None:
        try:
            prog = parse_program(text)
        except ScriptError as exc:
            self._message(f"Program rejected: {exc}", LEVEL_ERROR)
            return
        if prog is None:
            self._on_urscript(text)
            return
        with self._lock:
            self.interpreter.stop("", brake=False)  # a new program replaces the running one
            self._stop_runner()
            self._starting = None
            now = self.engine.controller_time_s() + self._t0_host
            self._starting = (prog, now + PROGRAM_START_S)

    def _on_urscript(self, text: str) -> None:
        """Any other program: compile the supported subset (or refuse it at once), then run."""
        try:
            program = compile_program(text)
        except URScriptError as exc:
            self._message(f"Compile error: {exc}", LEVEL_ERROR)
            return
        if program.secondary:  # runs beside the main program
            ScriptRunner(program, self.engine, self.regs, self._message, lambda r: None).start()
            return
        with self._lock:
            self.interpreter.stop("", brake=False)
            self._starting = None
            self._stop_runner()
            self._loaded = None
            self._start_runner(program)

    def _start_runner(self, program: Program) -> None:
        runner = ScriptRunner(program, self.engine, self.regs, self._message, self._runner_ended)
        self._runner = runner
        self.engine.set_program_running(True)
        runner.start()

    def _stop_runner(self) -> None:
        runner = self._runner
        if runner is not None and runner.running:
            runner.stop()

    def _runner_ended(self, runner: ScriptRunner) -> None:
        # called on the runner's thread: no controller lock here (stop_program joins it)
        if self._runner is runner and not self.interpreter.running:
            self.engine.set_program_running(False)

    def _message(self, text: str, level: int = LEVEL_INFO) -> None:
        log.info("%s: %s", self.host, text)
        self.messages.append(text)
        self.rtde.broadcast_text(text, level)

    def _apply_io(self, regs: RegisterFile) -> None:
        mask = regs.pending_io.pop("speed_slider_mask", None)
        fraction = regs.pending_io.pop("speed_slider_fraction", None)
        if mask == 1 and isinstance(fraction, float):
            try:
                self.engine.set_speed_fraction(fraction)
            except EngineError as exc:
                self._message(f"speed slider: {exc}", LEVEL_ERROR)

    # -- the controller cycle ------------------------------------------------------------------
    def _wants_cycles(self) -> bool:
        return (self.rtde.any_streaming() or self.interpreter.running
                or self._starting is not None or self.client_interfaces.any_realtime())

    def _cycle_once(self) -> None:
        """One controller cycle, run by the engine thread after it stepped the arm."""
        if self.faults.frozen or not self._alive:
            return
        with self._lock:
            now = self.engine.controller_time_s() + self._t0_host
            if self._starting is not None and now >= self._starting[1]:
                self.interpreter.start(self._starting[0])
                self._starting = None
            snap = self.engine.snapshot()
            self.interpreter.step(snap)
            if self.interpreter.running:
                snap = self.engine.snapshot()  # the step may have started a motion
        if not self.faults.stream_stalled():
            with self.regs.lock:
                view = ControllerView(snap, self.regs, self.runtime_state())
                packages = self.rtde.due_packages(view, snap.timestamp_s)
            self.rtde.send_packages(packages)
            self.client_interfaces.publish(view, snap.timestamp_s)

    # -- lifecycle -----------------------------------------------------------------------------
    @property
    def alive(self) -> bool:
        return self._alive

    def close(self, reset: bool = False) -> None:
        """Stop serving: listeners closed, clients dropped, engine stopped."""
        if not self._alive:
            return
        self._alive = False
        for service in (self.rtde.service, self.dashboard):
            service.frozen = False
            service.close(reset)
        self.client_interfaces.close(reset)
        self.engine.set_cycle_hook(None)
        self._stop_runner()
        if self._owns_engine:
            self.engine.close()

    def __enter__(self) -> URController:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
