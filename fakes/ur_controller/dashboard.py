"""The Dashboard server (port 29999): one text line in, one text line out.

Reply texts are the ones a PolyScope 5 dashboard gives and ur_rtde's DashboardClient compares
against (e.g. it requires exactly "Protective stop releasing", "Stopped", "Starting program"),
so they must not be paraphrased.
"""

from __future__ import annotations

import logging
import socket
from typing import Protocol

from fakes.ur_controller.tcp import TcpService
from fakes.ur_sim import EngineError, MotionEngine, SafetyMode

log = logging.getLogger(__name__)

DASHBOARD_PORT = 29999
GREETING = "Connected: Universal Robots Dashboard Server"
UNLOCK_REFUSED = (
    "Cannot unlock protective stop until 5s after occurrence. "
    "Always inspect cause of protective stop before unlocking"
)


class DashboardBackend(Protocol):
    """What the dashboard needs from the controller."""

    engine: MotionEngine
    remote_control: bool
    serial_number: str
    polyscope_version: str

    def program_state(self) -> str: ...  # "PLAYING", "STOPPED", "PAUSED"

    def program_name(self) -> str: ...

    def stop_program(self, reason: str) -> None: ...

    def loaded_program(self) -> str | None: ...

    def load_program(self, name: str) -> bool: ...

    def play(self) -> bool: ...

    def pause(self) -> bool: ...


def reply_to(line: str, ctl: DashboardBackend) -> str:
    """The dashboard's answer to one command line (without the trailing newline)."""
    cmd = line.strip()
    low = cmd.lower()
    engine = ctl.engine
    if low == "power on":
        _quietly(engine.power_on)
        return "Powering on"
    if low == "power off":
        _quietly(engine.power_off)
        return "Powering off"
    if low == "brake release":
        _quietly(engine.brake_release)
        return "Brake releasing"
    if low == "robotmode":
        return f"Robotmode: {engine.snapshot().robot_mode.name}"
    if low == "safetymode":
        return f"Safetymode: {engine.snapshot().safety_mode.name}"
    if low == "safetystatus":
        return f"Safetystatus: {engine.snapshot().safety_mode.name}"
    if low == "unlock protective stop":
        if engine.snapshot().safety_mode == SafetyMode.PROTECTIVE_STOP and not (
                engine.unlock_protective_stop()):
            return UNLOCK_REFUSED
        return "Protective stop releasing"
    if low == "close safety popup":
        return "closing safety popup"
    if low == "close popup":
        return "closing popup"
    if low.startswith("popup "):
        return "showing popup"
    if low == "stop":
        ctl.stop_program("stopped from the dashboard")
        return "Stopped"
    if low == "play":
        return "Starting program" if ctl.play() else "Failed to execute: play"
    if low == "pause":
        return "Pausing program" if ctl.pause() else "Failed to execute: pause"
    if low == "programstate":
        return f"{ctl.program_state()} {ctl.program_name()}"
    if low == "running":
        return f"Program running: {str(ctl.program_state() == 'PLAYING').lower()}"
    if low == "get loaded program":
        loaded = ctl.loaded_program()
        return f"Loaded program: {loaded}" if loaded else "No program loaded"
    if low.startswith("load "):
        name = cmd[5:].strip()
        return (f"Loading program: {name}" if ctl.load_program(name)
                else f"File not found: {name}")
    if low == "polyscopeversion":
        return f"URSoftware {ctl.polyscope_version} (Oct 15 2021)"
    if low == "get serial number":
        return ctl.serial_number
    if low == "get robot model":
        return "UR5"
    if low == "is in remote control":
        return str(ctl.remote_control).lower()
    if low == "isprogramsaved":
        return "true <unnamed>"
    if low.startswith("addtolog "):
        return "Added log message"
    if low == "restart safety":
        return "Restarting safety"
    if low == "quit":
        return "Disconnected"
    if low == "shutdown":
        return "Shutting down"
    return f"could not understand: '{cmd}'"


def _quietly(action: object) -> None:
    """Power and brake requests the arm cannot honour (e.g. under e-stop) are acknowledged
    but change nothing, as on a real dashboard."""
    try:
        action()  # type: ignore[operator]
    except EngineError as exc:
        log.info("dashboard request not honoured: %s", exc)


class DashboardSession:
    """One dashboard client: greeting, then a reply per received line."""

    def __init__(self, sock: socket.socket, ctl: DashboardBackend) -> None:
        self._sock = sock
        self._ctl = ctl
        self._buf = b""

    def on_open(self) -> None:
        self._sock.sendall((GREETING + "\n").encode())

    def feed(self, data: bytes) -> bool:
        self._buf += data
        while b"\n" in self._buf:
            raw, self._buf = self._buf.split(b"\n", 1)
            answer = reply_to(raw.decode(errors="replace"), self._ctl)
            self._sock.sendall((answer + "\n").encode())
            if answer == "Disconnected":
                return False
        return True

    def on_close(self) -> None:
        pass


def dashboard_service(host: str, ctl: DashboardBackend, port: int = DASHBOARD_PORT) -> TcpService:
    """The dashboard server on ``host:29999``."""
    return TcpService(host, port, "dashboard", lambda sock: DashboardSession(sock, ctl))
