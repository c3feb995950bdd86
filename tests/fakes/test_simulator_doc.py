"""docs/simulator.md's power-on step runs as written (Python only, nothing a fresh machine
lacks) and brings the standalone simulated controller to RUNNING."""

from __future__ import annotations

import re
import socket
import subprocess
import sys
from pathlib import Path

from fakes.ur_controller.process import ControllerProcess
from tests.support.waiting import wait_until

ROOT = Path(__file__).resolve().parents[2]


def power_on_block() -> str:
    """The Python of the doc's ``.venv/bin/python - <<'EOF'`` block."""
    text = (ROOT / "docs" / "simulator.md").read_text()
    match = re.search(r"```\n\.venv/bin/python - <<'EOF'\n(.*?)\nEOF\n```", text, re.DOTALL)
    assert match, "docs/simulator.md has no power-on block"
    return match.group(1)


def robot_mode(host: str) -> str:
    with socket.create_connection((host, 29999), timeout=5) as s:
        f = s.makefile("rw")
        f.readline()
        f.write("robotmode\n")
        f.flush()
        return f.readline().strip()


def test_the_documented_power_on_brings_the_controller_to_running() -> None:
    block = power_on_block()
    assert "nc " not in block and "127.0.0.2" in block
    controller = ControllerProcess()  # powered off, as a real boot; a free loopback address
    try:
        assert robot_mode(controller.host) != "Robotmode: RUNNING"
        out = subprocess.run([sys.executable, "-"], input=block.replace(
            "127.0.0.2", controller.host), text=True, capture_output=True, timeout=30)
        assert out.returncode == 0, out.stderr
        assert out.stdout.splitlines()[1:] == ["Powering on", "Brake releasing"], out.stdout
        wait_until(lambda: robot_mode(controller.host) == "Robotmode: RUNNING", 15.0,
                   "the controller to run", poll_s=0.2)
    finally:
        controller.close()
