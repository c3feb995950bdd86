"""Deployment on a cell PC: the systemd unit in the repo passes ``systemd-analyze verify`` (when
systemd is present) and says what docs/deployment.md promises, and ``cell serve --log-format json``
writes one JSON object per line, the service's own records and uvicorn's access log alike."""

from __future__ import annotations

import json
import re
import shutil
import subprocess
import sys
import time
from pathlib import Path

import httpx
import pytest

from cell.config.schema import load_config
from fakes.ur_controller.process import free_loopback_host
from tests.support.cell import AUTH, without_interfaces
from tests.support.net import free_port
from tests.support.paths import REPO

UNIT = REPO / "cell" / "deploy" / "ur-vision-cell.service"
INSTALLED_CELL = "/opt/ur-vision-cell/.venv/bin/cell"


def _unit_settings() -> dict[str, list[str]]:
    out: dict[str, list[str]] = {}
    for line in UNIT.read_text().splitlines():
        if "=" in line and not line.startswith("#"):
            key, value = line.split("=", 1)
            out.setdefault(key.strip(), []).append(value.strip())
    return out


def test_unit_runs_the_service_as_its_user_with_restarts_state_and_journald() -> None:
    s = _unit_settings()
    assert s["User"] == ["urcell"] and s["Group"] == ["urcell"]
    assert s["Restart"] == ["on-failure"]
    assert s["StandardOutput"] == ["journal"] and s["StandardError"] == ["journal"]
    # the state directory is the real example's [api] state_dir
    example = load_config(REPO / "cell" / "configs" / "real-cell.example.toml")
    assert "/var/lib/" + s["StateDirectory"][0] == example.api.state_dir
    assert s["ExecStart"][0].split() == [
        INSTALLED_CELL, "serve", "--config", "/etc/ur-vision-cell/cell.toml", "--host",
        "0.0.0.0", "--port", "8000", "--log-format", "json"]
    assert s["ExecStartPre"][0].split()[1:] == ["config", "check",
                                                "/etc/ur-vision-cell/cell.toml"]
    assert s["WantedBy"] == ["multi-user.target"]


def test_unit_sets_the_limits_a_long_run_needs() -> None:
    """Open files well above systemd's default soft limit of 1024 (sockets of many clients,
    the databases, the image log, the ur_rtde pipes), and a bound on tasks that is no
    tighter than the service's own threads need."""
    s = _unit_settings()
    assert s.get("LimitNOFILE") == ["65536"], s.get("LimitNOFILE")
    assert s.get("LimitMEMLOCK") == ["infinity"], s.get("LimitMEMLOCK")
    assert len(s.get("TasksMax", [])) == 1 and int(s["TasksMax"][0]) >= 1024, s.get("TasksMax")


@pytest.mark.skipif(shutil.which("systemd-analyze") is None, reason="systemd is not present")
def test_unit_passes_systemd_analyze_verify(tmp_path: Path) -> None:
    # verify also checks that the executables exist: point them at this checkout's cell
    cell = Path(sys.executable).with_name("cell")
    if not cell.exists():
        pytest.skip("the cell console script is not installed in this environment")
    unit = tmp_path / UNIT.name
    unit.write_text(UNIT.read_text().replace(INSTALLED_CELL, str(cell)))
    out = subprocess.run(["systemd-analyze", "verify", str(unit)], capture_output=True,
                         text=True, timeout=60)
    assert out.returncode == 0, out.stdout + out.stderr
    assert "ur-vision-cell.service" not in out.stderr, out.stderr  # no warnings about it


def test_serve_log_format_json(tmp_path: Path) -> None:
    text = (REPO / "cell" / "configs" / "sim.toml").read_text()
    text = text.replace('kind = "ur"', 'kind = "sim"').replace("ur_controller = true",
                                                               "ur_controller = false")
    text = re.sub(r'(\[gripper\]\s*)kind = "sim"', r'\1kind = "none"', text)
    text = text.replace('job_db = "var/cell_jobs.db"', 'job_db = "jobs.db"').replace(
        "[api]\n", f'[api]\nstate_dir = "{tmp_path / "state"}"\n', 1)
    config = tmp_path / "cell.toml"
    config.write_text(without_interfaces(text))
    host = free_loopback_host()
    port = free_port(host)
    proc = subprocess.Popen(
        [sys.executable, "-m", "cell", "serve", "--config", str(config), "--host", host,
         "--port", str(port), "--log-format", "json"],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, cwd=tmp_path)
    url = f"http://{host}:{port}"
    try:
        deadline = time.monotonic() + 90
        while True:
            assert proc.poll() is None, proc.communicate()
            try:
                if httpx.get(f"{url}/api/v1/health", timeout=1).status_code == 200:
                    break
            except httpx.TransportError:
                pass
            assert time.monotonic() < deadline, "the service did not come up within 90 s"
            time.sleep(0.2)
        r = httpx.get(f"{url}/api/v1/status", headers=AUTH["viewer"], timeout=10)
        assert r.status_code == 200
    finally:
        proc.terminate()
        try:
            stdout, stderr = proc.communicate(timeout=20)
        except subprocess.TimeoutExpired:
            proc.kill()
            stdout, stderr = proc.communicate()
    records = [json.loads(line) for line in stderr.splitlines() if line.strip()]
    assert stdout.strip() == ""  # nothing outside the log records
    assert all({"time", "level", "logger", "message"} <= set(r) for r in records), records
    messages = [r["message"] for r in records]
    assert any(m.startswith("serving the cell on") and str(tmp_path / "state") in m
               for m in messages), messages
    assert any(r["logger"] == "uvicorn.access" and "/api/v1/status" in r["message"]
               for r in records), messages
    # the state lives in state_dir, not in the working directory
    assert (tmp_path / "state" / "jobs.db").exists()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["cell.toml", "state"]
