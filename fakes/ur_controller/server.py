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

from fakes.ur_controller.dashboard import dashboard_service
from fakes.ur_controller.faults import Faults
from fakes.ur_controller.registers import ControllerView, RegisterFile
from fakes.ur_controller.rtde import LEVEL_ERROR, LEVEL_INFO, RTDEServer
from fakes.ur_controller.script import (
    RUNTIME_PLAYING,
    RUNTIME_STOPPED,
    ControlProgram,
    MailboxInterpreter,
    ScriptError,
    parse_program,
    script_service,
)
from fakes.ur_sim import EngineError, MotionEngine

log = logging.getLogger(__name__)

CONTROLLER_VERSION = (5, 11, 1, 108318)  # >= 5.11: ur_rtde streams at 500 Hz
CYCLE_S = 0.002
IDLE_CYCLE_S = 0.02  # nobody streams: the program still steps, just less often
# A real controller takes tens of milliseconds to compile and start an uploaded program. The
# delay matters: ur_rtde stops its script, clears the command register over RTDE and uploads
# a new script over another socket; a program started at once could still read the stop
# command and end (seen as a rare hang of movePath waiting for the program to run).
PROGRAM_START_S = 0.08


class URController:
    """A simulated controller serving ``host``. Use as a context manager or call close()."""

    def __init__(
        self, host: str = "127.0.0.2", engine: MotionEngine | None = None, *,
        remote_control: bool = True, serial_number: str = "20235500042",
        rtde_port: int = 30004, script_port: int = 30003, dashboard_port: int = 29999,
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
        self.rtde = RTDEServer(host, self.regs, CONTROLLER_VERSION, self._apply_io, rtde_port)
        self.script = script_service(host, self._on_program, script_port)
        self.dashboard = dashboard_service(host, self, dashboard_port)
        self.faults = Faults(self)
        self._alive = True
        self._t0_host = self.engine.snapshot().host_monotonic_s - self.engine.controller_time_s()
        self.engine.set_cycle_hook(self._cycle_once, self._wants_cycles, IDLE_CYCLE_S)

    # -- program ------------------------------------------------------------------------------
    def program_state(self) -> str:
        return "PLAYING" if self.interpreter.running else "STOPPED"

    def program_name(self) -> str:
        return "rtde_control" if self.interpreter.running else "<unnamed>"

    def runtime_state(self) -> int:
        return RUNTIME_PLAYING if self.interpreter.running else RUNTIME_STOPPED

    def stop_program(self, reason: str) -> None:
        with self._lock:
            self._starting = None
            self.interpreter.stop(reason)

    def _on_program(self, text: str) -> None:
        try:
            prog = parse_program(text)
        except ScriptError as exc:
            self._message(f"Program rejected: {exc}", LEVEL_ERROR)
            return
        with self._lock:
            self.interpreter.stop("", brake=False)  # a new program replaces the running one
            self._starting = None
            if prog is None:
                self._message("The simulator runs only the ur_rtde control script; "
                              "other URScript programs are not executed", LEVEL_ERROR)
                return
            now = self.engine.controller_time_s() + self._t0_host
            self._starting = (prog, now + PROGRAM_START_S)

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
        return self.rtde.any_streaming() or self.interpreter.running or self._starting is not None

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

    # -- lifecycle -----------------------------------------------------------------------------
    @property
    def alive(self) -> bool:
        return self._alive

    def close(self, reset: bool = False) -> None:
        """Stop serving: listeners closed, clients dropped, engine stopped."""
        if not self._alive:
            return
        self._alive = False
        for service in (self.rtde.service, self.script, self.dashboard):
            service.frozen = False
            service.close(reset)
        self.engine.set_cycle_hook(None)
        if self._owns_engine:
            self.engine.close()

    def __enter__(self) -> URController:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
