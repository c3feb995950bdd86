"""A line-based control channel (stdin -> stdout, one JSON reply per line) for a controller in
its own process, so tests can inspect it and inject faults from outside.

ur_rtde's Python constructors hold the GIL while they talk to the controller, so a client and a
simulated controller cannot share one Python process: tests run the controller as
``python -m fakes.ur_controller --control`` and drive it through :class:`ControllerProcess`.
"""

from __future__ import annotations

import json
import os
import signal
from typing import IO, Any

from fakes.ur_controller.server import URController
from fakes.ur_sim import SafetyPlane


def state_of(ctl: URController) -> dict[str, Any]:
    snap = ctl.engine.snapshot()
    return {
        "q": list(snap.q),
        "tcp_pose": list(snap.tcp_pose),
        "tcp_offset": list(snap.tcp_offset),
        "robot_mode": snap.robot_mode.name,
        "safety_mode": snap.safety_mode.name,
        "active_command": snap.active_command,
        "moving": snap.moving,
        "program": ctl.program_state(),
        "messages": ctl.messages[-20:],
        "host_monotonic_s": snap.host_monotonic_s,
        "controller_lag_s": ctl.engine.lag_s(),
        "skipped_cycles": ctl.engine.skipped_cycles,
    }


def handle(ctl: URController, line: str) -> dict[str, Any]:
    """Run one control command; the reply always has ``ok``."""
    words = line.split()
    if not words:
        return {"ok": False, "error": "empty command"}
    cmd, args = words[0], [float(w) for w in words[1:] if _is_number(w)]
    f = ctl.faults
    if cmd == "state":
        return {"ok": True, **state_of(ctl)}
    if cmd == "power":
        ctl.engine.brake_release()
    elif cmd == "pstop":
        f.protective_stop(args[0] if args else 0.0)
    elif cmd == "estop":
        f.emergency_stop(args[0] if args else 0.0)
    elif cmd == "estop-release":
        f.release_emergency_stop()
    elif cmd == "drop":
        f.drop_connections(reset="reset" in words)
    elif cmd == "stall":
        f.stall_stream(args[0] if args else 1.0)
    elif cmd == "freeze":
        f.freeze()
    elif cmd == "contact":
        ctl.engine.set_contact_planes([SafetyPlane.floor(args[0])] if args else [])
    elif cmd == "remote":
        ctl.remote_control = "off" not in words
    elif cmd == "kill":
        os.kill(os.getpid(), signal.SIGKILL)
    else:
        return {"ok": False, "error": f"unknown command {cmd!r}"}
    return {"ok": True}


def _is_number(word: str) -> bool:
    try:
        float(word)
    except ValueError:
        return False
    return True


def serve(ctl: URController, stdin: IO[str], stdout: IO[str]) -> None:
    """Answer control lines until stdin closes."""
    for line in stdin:
        try:
            reply = handle(ctl, line)
        except Exception as exc:  # a bad command must not take the controller down
            reply = {"ok": False, "error": str(exc)}
        stdout.write(json.dumps(reply) + "\n")
        stdout.flush()
