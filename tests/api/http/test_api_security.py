"""Security of the HTTP API on the simulated cell (roles, limits, TLS, token rules):
header-only credentials on motion routes, JSON-only bodies, authentication before the body is
read, a body cap, audited refusals, constant-time and hashed tokens, no token in any log line,
HTTPS from ``cell serve``."""

from __future__ import annotations

import logging
import os
import shutil
import socket
import ssl
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import httpx
import pytest
import uvicorn
from fastapi.testclient import TestClient

from api.app import create_app
from api.auth import TokenTable, token_digest
from cell.config.schema import TokenConfig
from cell.service import Cell
from cell.supervision.status import still_starting
from tests.support.cell import AUTH, running_cell, sim_config, tcp
from tests.support.paths import REPO

OP, PLC, VIEW = AUTH["operator"], AUTH["plc"], AUTH["viewer"]


@pytest.fixture
def client(tmp_path: Path) -> Iterator[TestClient]:
    with running_cell(sim_config(tmp_path)) as cell, TestClient(create_app(cell)) as c:
        yield c


def cell_of(client: TestClient) -> Cell:
    cell: Cell = client.app.state.cell  # type: ignore[attr-defined]
    return cell


def audit(client: TestClient) -> list[dict[str, Any]]:
    return list(client.get("/api/v1/audit", headers=VIEW).json()["entries"])


def code(r: httpx.Response) -> str:
    return str(r.json()["error"]["code"])


def test_cross_site_simple_post_moves_nothing(client: TestClient) -> None:
    before = tcp(cell_of(client))
    form = {"Content-Type": "application/x-www-form-urlencoded"}
    r = client.post("/api/v1/approach?token=sim-plc", headers=form)
    assert r.status_code == 401 and code(r) == "unauthorized"
    r = client.post("/api/v1/approach?token=sim-plc", json={"standoff_mm": 50})
    assert r.status_code == 401, "?token= must not authorise a POST"
    r = client.post("/api/v1/approach", headers={**PLC, **form}, content=b"standoff_mm=50")
    assert r.status_code == 415 and code(r) == "unsupported_media_type"
    r = client.post("/api/v1/approach", headers={**PLC, "Content-Type": "text/plain"})
    assert r.status_code == 415
    r = client.post("/api/v1/approach", headers=PLC, content=b'{"standoff_mm": 50}')
    assert r.status_code == 415, "a body without a content type is refused"
    assert client.get("/api/v1/jobs", headers=VIEW).json()["jobs"] == []
    assert abs(tcp(cell_of(client)) - before).max() < 1e-6
    rows = [e for e in audit(client) if e["command"] == "POST /api/v1/approach"]
    assert {e["outcome"] for e in rows} == {"refused:unauthorized",
                                            "refused:unsupported_media_type"}
    assert any(e["caller"] == "anonymous" for e in rows)
    assert any(e["caller"] == "http:plc(plc)" for e in rows)


def test_query_token_only_on_get_streaming_routes(client: TestClient) -> None:
    assert client.get("/api/v1/status?token=sim-viewer").status_code == 401
    assert client.get("/api/v1/camera/frame.jpg?token=sim-viewer").status_code == 200
    assert client.get("/api/v1/camera/frame.png?token=sim-viewer").status_code == 200
    r = client.get("/api/v1/events?token=sim-viewer&max_events=1")
    assert r.status_code == 200 and "event:" in r.text
    assert client.post("/api/v1/stop?token=sim-viewer").status_code == 401
    assert client.post("/api/v1/stop", headers=VIEW).status_code == 200


def test_authentication_comes_before_the_body(client: TestClient) -> None:
    # 401 before 422: an anonymous malformed body is not parsed
    r = client.post("/api/v1/jog", content=b"{not json", headers={"Content-Type":
                                                                 "application/json"})
    assert r.status_code == 401
    r = client.post("/api/v1/jog", json={"mode": "sideways"})
    assert r.status_code == 401
    r = client.post("/api/v1/jog", json={"mode": "sideways"}, headers=OP)
    assert r.status_code == 422 and code(r) == "invalid_request"
    # 413 for a large body, after authentication; anonymous ones are never read (a STOP
    # without a token is taken, so its body is capped as every other)
    big = b'{"reason": "' + b"x" * 200_000 + b'"}'
    r = client.post("/api/v1/stop", content=big, headers={**VIEW,
                                                          "Content-Type": "application/json"})
    assert r.status_code == 413 and code(r) == "body_too_large"
    r = client.post("/api/v1/approach", content=big,
                    headers={"Content-Type": "application/json"})
    assert r.status_code == 401
    r = client.post("/api/v1/stop", content=big, headers={"Content-Type": "application/json"})
    assert r.status_code == 413 and code(r) == "body_too_large"
    # 403 for a valid token of the wrong role
    assert client.post("/api/v1/jog", json={"mode": "step"}, headers=VIEW).status_code == 403
    rows = audit(client)
    assert any(e["command"] == "POST /api/v1/jog" and e["outcome"] == "refused:invalid_request"
               and e["caller"] == "http:operator(operator)" for e in rows)
    assert any(e["command"] == "POST /api/v1/jog" and e["outcome"] == "refused:forbidden"
               and e["caller"] == "http:viewer(viewer)" for e in rows)
    assert any(e["command"] == "POST /api/v1/jog" and e["outcome"] == "refused:unauthorized"
               and e["caller"] == "anonymous" for e in rows)
    assert any(e["outcome"] == "refused:body_too_large" and e["caller"] == "http:viewer(viewer)"
               for e in rows)


def test_hashed_tokens_and_constant_time_lookup() -> None:
    salt = "c3lt"
    table = TokenTable([
        TokenConfig(role="plc", name="line-3",
                                    sha256=token_digest("long-secret-plc-token", salt),
                                    salt=salt),
        TokenConfig(token="sim-viewer", role="viewer")], simulated=True)
    assert table.lookup("long-secret-plc-token").role == "plc"
    assert table.lookup("sim-viewer").role == "viewer"
    for bad in ("long-secret-plc-toke", "long-secret-plc-token ", "", "x" * 500):
        with pytest.raises(Exception, match="token"):
            table.lookup(bad)


class _Lines(logging.Handler):
    def __init__(self) -> None:
        super().__init__(logging.DEBUG)
        self.lines: list[str] = []

    def emit(self, record: logging.LogRecord) -> None:
        self.lines.append(self.format(record))


def test_no_token_in_any_log_line(tmp_path: Path) -> None:
    """A real uvicorn with its access log on: every line the service logs is captured."""
    capture = _Lines()
    capture.setFormatter(logging.Formatter("%(name)s %(message)s"))
    with running_cell(sim_config(tmp_path)) as cell:
        app = create_app(cell)
        sock = socket.socket()
        sock.bind(("127.0.0.1", 0))
        port = sock.getsockname()[1]
        server = uvicorn.Server(uvicorn.Config(app, log_level="info", access_log=True))
        thread = threading.Thread(target=server.run, kwargs={"sockets": [sock]}, daemon=True)
        thread.start()
        deadline = time.monotonic() + 20
        while not server.started:
            assert time.monotonic() < deadline and thread.is_alive()
            time.sleep(0.02)
        loggers = [logging.getLogger(n) for n in ("", "uvicorn", "uvicorn.access",
                                                  "uvicorn.error")]
        for lg in loggers:
            lg.addHandler(capture)
        try:
            base = f"http://127.0.0.1:{port}/api/v1"
            httpx.get(f"{base}/camera/frame.jpg?overlay=true&token=sim-viewer", timeout=10)
            httpx.get(f"{base}/events?max_events=1&token=sim-operator", timeout=10)
            httpx.post(f"{base}/stop?token=sim-plc", timeout=10)
            httpx.get(f"{base}/status?token=sim-viewer", timeout=10)
            httpx.get(f"{base}/status", headers={"Authorization": "Bearer sim-operator"},
                      timeout=10)
            logging.getLogger("cell.test").warning("client asked for /x?token=sim-viewer")
            time.sleep(0.3)
        finally:
            for lg in loggers:
                lg.removeHandler(capture)
            server.should_exit = True
            thread.join(10)
            sock.close()
    access = [line for line in capture.lines if "uvicorn.access" in line]
    print(f"{len(capture.lines)} log lines, {len(access)} access lines; e.g. {access[:1]}")
    assert len(access) >= 5, capture.lines
    assert any("token=[redacted]" in line for line in access)
    for line in capture.lines:
        assert "sim-viewer" not in line and "sim-operator" not in line \
            and "sim-plc" not in line, line


@pytest.mark.timeout(180)
def test_cell_serve_https(tmp_path: Path) -> None:
    if shutil.which("openssl") is None:
        pytest.skip("openssl is needed to make a test certificate")
    cert, key = tmp_path / "cert.pem", tmp_path / "key.pem"
    subprocess.run(["openssl", "req", "-x509", "-newkey", "rsa:2048", "-nodes", "-days", "1",
                    "-subj", "/CN=127.0.0.1", "-addext", "subjectAltName=IP:127.0.0.1",
                    "-keyout", str(key), "-out", str(cert)],
                   check=True, capture_output=True, timeout=60)
    from tests.support.browser import free_port
    from tests.support.browser import sim_config as page_sim_config

    trust = ssl.create_default_context(cafile=str(cert))
    port = free_port()
    log = (tmp_path / "serve.log").open("w")
    proc = subprocess.Popen(
        [sys.executable, "-m", "cell", "serve", "--config", str(page_sim_config(tmp_path)),
         "--port", str(port), "--log-level", "warning", "--ssl-certfile", str(cert),
         "--ssl-keyfile", str(key)], cwd=tmp_path, stdout=log, stderr=subprocess.STDOUT,
        env={**os.environ, "PYTHONPATH": str(REPO)})
    try:
        deadline = time.monotonic() + 120
        while True:
            assert proc.poll() is None, (tmp_path / "serve.log").read_text()
            try:
                r = httpx.get(f"https://127.0.0.1:{port}/api/v1/health", verify=trust,
                              timeout=2)
                if not still_starting(r.json()):
                    break
            except httpx.HTTPError:
                pass
            assert time.monotonic() < deadline, (tmp_path / "serve.log").read_text()
            time.sleep(0.3)
        assert r.status_code == 200 and r.json()["status"] == "ok"
        with pytest.raises(httpx.HTTPError):
            httpx.get(f"http://127.0.0.1:{port}/api/v1/health", timeout=2)
    finally:
        proc.terminate()
        proc.wait(20)
        log.close()
    bad = subprocess.run([sys.executable, "-m", "cell", "serve", "--ssl-certfile", str(cert)],
                         capture_output=True, text=True, timeout=60,
                         env={**os.environ, "PYTHONPATH": str(REPO)})
    assert bad.returncode == 2 and "--ssl-keyfile" in bad.stderr


def test_a_flood_of_refusals_does_not_fill_the_audit_log(client: TestClient) -> None:
    from api.http.refusals import AUDIT_REFUSALS_PER_S, audit_refusal

    app = client.app
    for _ in range(3 * AUDIT_REFUSALS_PER_S):
        audit_refusal(app, "anonymous", "GET", "/api/v1/flood", 401, "unauthorized", "x")
    time.sleep(1.1)  # the next second: the next row says how many were not written
    audit_refusal(app, "anonymous", "GET", "/api/v1/flood", 401, "unauthorized", "x")
    rows = [e for e in cell_of(client).jobs.audit_log(1000)
            if e.command == "GET /api/v1/flood"]
    skipped = sum(e.params.get("refusals_not_written_before", 0) for e in rows)
    print(f"{len(rows)} rows written, {skipped} counted as skipped")
    assert len(rows) <= 2 * AUDIT_REFUSALS_PER_S + 1
    assert len(rows) - 1 + skipped == 3 * AUDIT_REFUSALS_PER_S
    assert skipped > 0


def _raw_post(base_url: str, path: str, headers: dict[str, str]) -> bytes:
    """Send only the head of a POST announcing a 10 MB body, then read the answer."""
    host, port = base_url.removeprefix("http://").split(":")
    head = f"POST {path} HTTP/1.1\r\nHost: {host}\r\nContent-Type: application/json\r\n" \
           "Content-Length: 10000000\r\n" + "".join(f"{k}: {v}\r\n" for k, v in headers.items())
    with socket.create_connection((host, int(port)), timeout=10) as s:
        s.sendall(head.encode() + b"\r\n" + b"{" * 1000)  # a token of the body, no more
        return s.recv(4096)


def test_large_bodies_are_answered_before_they_are_sent(tmp_path: Path) -> None:
    """The answer comes while the client still has 10 MB to send: the service never waited
    for (or buffered) the body of an anonymous or oversized request."""
    from tests.support.browser import serve_app

    with running_cell(sim_config(tmp_path)) as cell, serve_app(create_app(cell)) as url:
        t0 = time.monotonic()
        anonymous = _raw_post(url, "/api/v1/approach", {})
        authorised = _raw_post(url, "/api/v1/approach", {"Authorization": "Bearer sim-plc"})
        elapsed = time.monotonic() - t0
        assert cell.jobs.list_jobs() == []
    print(f"answers in {elapsed:.3f} s: {anonymous.splitlines()[0]!r}, "
          f"{authorised.splitlines()[0]!r}")
    assert anonymous.startswith(b"HTTP/1.1 401")
    assert authorised.startswith(b"HTTP/1.1 413")
