"""Ctrl-C on ``cell serve`` as a terminal sends it: SIGINT to the whole process group (the
service, its ur_rtde child and the simulated controller). The service stops the arm and exits
cleanly; no child dies first, so nothing logs a lost arm, and the next start has no alarm."""

from __future__ import annotations

import os
import re
import signal
import subprocess
import sys
import time
from importlib import resources
from pathlib import Path

import httpx

from fakes.ur_controller.process import free_loopback_host
from tests.support.cell import AUTH, without_interfaces
from tests.support.net import free_port


def _config(tmp_path: Path) -> Path:
    """The built-in sim config as `make run` serves it (simulated controller through ur_rtde),
    on a loopback address of its own and with a job database under tmp_path."""
    text = resources.files("cell.configs").joinpath("sim.toml").read_text()
    text = re.sub(r'(\n\[robot\]\n(?:(?!\n\[)[\s\S])*?\n)host = "[^"]*"',
                  rf'\1host = "{free_loopback_host()}"', text)
    text = text.replace('job_db = "var/cell_jobs.db"', f'job_db = "{tmp_path / "jobs.db"}"')
    path = tmp_path / "cell.toml"
    path.write_text(without_interfaces(text))
    return path


def _serve_then_ctrl_c(config: Path) -> tuple[int, str, int]:
    """(exit code, output, active alarms seen while serving)."""
    port = free_port()
    proc = subprocess.Popen(
        [sys.executable, "-m", "cell", "serve", "--config", str(config), "--port", str(port)],
        stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, start_new_session=True)
    url = f"http://127.0.0.1:{port}/api/v1"
    try:
        deadline = time.monotonic() + 90
        while True:
            assert proc.poll() is None, proc.communicate()[0]
            try:
                r = httpx.get(f"{url}/health", timeout=1)
                if r.status_code == 200 and r.json().get("status") == "ok":
                    break
            except httpx.TransportError:
                pass
            assert time.monotonic() < deadline, "the service did not become healthy in 90 s"
            time.sleep(0.3)
        time.sleep(1.5)  # the alarm watch has looked at least twice
        alarms = httpx.get(f"{url}/alarms", params={"active_only": "true"},
                           headers=AUTH["viewer"], timeout=5).json()
        os.killpg(proc.pid, signal.SIGINT)
        out, _ = proc.communicate(timeout=60)
        return proc.returncode, out, int(alarms["active"])
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait()


def test_ctrl_c_stops_cleanly_and_leaves_no_alarm_for_the_next_start(tmp_path: Path) -> None:
    config = _config(tmp_path)
    code, out, _ = _serve_then_ctrl_c(config)
    assert code == 0, out[-3000:]
    assert "link lost" not in out, out[-3000:]
    assert "Traceback" not in out, out[-3000:]
    code, out, active = _serve_then_ctrl_c(config)
    assert active == 0, out[-3000:]
    assert code == 0, out[-3000:]
