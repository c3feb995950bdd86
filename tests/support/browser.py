"""Helpers for the operator-page tests: Debian's headless Chromium driven by Playwright, servers
to point it at (the simulated cell as a subprocess, or an in-process app), and a small
recording API that answers like the real one so page behaviour can be checked request by
request.

No browser is ever downloaded: the tests use /usr/bin/chromium (``make browser`` installs it)
and skip with a reason when it is absent.
"""

from __future__ import annotations

import json
import os
import re
import socket
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import cv2
import httpx
import numpy as np
import pytest
import uvicorn
from fastapi import FastAPI, Request
from fastapi.responses import JSONResponse, Response

from cell.supervision.status import still_starting
from tests.support.cell import without_interfaces
from tests.support.net import free_port
from tests.support.paths import REPO

ARTIFACTS = REPO / "test-artifacts"
CHROMIUM = Path(os.environ.get("CELL_CHROMIUM", "/usr/bin/chromium"))
CHROMIUM_ARGS = [
    "--headless",
    "--no-sandbox",
    "--disable-gpu",
    "--disable-quic",
    "--no-first-run",
    "--disable-background-networking",
    "--disable-component-update",
    "--disable-sync",
]


def require_chromium() -> Path:
    """The browser binary, or a clean skip saying how to get it."""
    if not CHROMIUM.is_file() or not os.access(CHROMIUM, os.X_OK):
        pytest.skip(f"{CHROMIUM} is missing: run `make browser` (as root) to install chromium")
    try:
        import playwright.sync_api  # noqa: F401
    except ImportError:
        pytest.skip("the playwright Python package is not installed (pip install -e '.[dev]')")
    return CHROMIUM


@contextmanager
def browser_context() -> Iterator[Any]:
    """A headless Chromium with a fresh profile (its own --user-data-dir, removed afterwards).

    Playwright forbids --user-data-dir in ``args``; a persistent context on a temporary
    directory is its way of giving the browser exactly that. Each new page of the context has
    its own sessionStorage, so a new page is a new operator session.
    """
    exe = require_chromium()
    from playwright.sync_api import sync_playwright

    with tempfile.TemporaryDirectory(prefix="cell-chromium-") as profile, sync_playwright() as pw:
        ctx = pw.chromium.launch_persistent_context(
            profile,
            executable_path=str(exe),
            headless=True,
            args=CHROMIUM_ARGS,
            viewport={"width": 1280, "height": 900},
        )
        ctx.set_default_timeout(15_000)
        try:
            yield ctx
        finally:
            ctx.close()


def login(page: Any, base_url: str, token: str) -> None:
    """Open the page and log in the way an operator does; waits until the role is shown."""
    page.goto(base_url + "/")
    page.get_by_test_id("token").fill(token)
    page.get_by_test_id("login").click()
    page.get_by_test_id("role").filter(has_text="role:").wait_for()


def screenshot(page: Any, name: str) -> Path:
    """Keep a picture of the page as a test artefact (test-artifacts/ is gitignored)."""
    ARTIFACTS.mkdir(exist_ok=True)
    path = ARTIFACTS / f"{name}.png"
    page.evaluate("window.scrollTo(0, 0)")  # else the sticky header lands mid-picture
    page.screenshot(path=str(path), full_page=True)
    return path


@contextmanager
def serve_app(app: FastAPI) -> Iterator[str]:
    """Run an ASGI app with uvicorn in a thread; yields its base URL."""
    sock = socket.socket()
    sock.bind(("127.0.0.1", 0))
    port = sock.getsockname()[1]
    server = uvicorn.Server(uvicorn.Config(app, log_level="warning", lifespan="on"))
    thread = threading.Thread(target=server.run, kwargs={"sockets": [sock]}, daemon=True)
    thread.start()
    deadline = time.monotonic() + 20
    while not server.started:
        if time.monotonic() > deadline or not thread.is_alive():
            raise RuntimeError("the test server did not start")
        time.sleep(0.02)
    try:
        yield f"http://127.0.0.1:{port}"
    finally:
        server.should_exit = True
        thread.join(10)
        sock.close()


def sim_config(workdir: Path) -> Path:
    """The built-in simulated cell's config with the in-process simulated arm (the same motion
    engine as the simulated UR controller, but no listening sockets: the controller's ports are
    the fixed UR ones, which parallel test runs would fight over) and the job database inside
    ``workdir``. The UR wire path is tested by the service's own tests."""
    text = (REPO / "cell" / "configs" / "sim.toml").read_text()
    robot_table = text.index("[robot]")
    head, tail = text[:robot_table], text[robot_table:]
    tail, n_kind = re.subn(r'^kind = ".*"$', 'kind = "sim"', tail, count=1, flags=re.M)
    tail, n_db = re.subn(r'^job_db = ".*"$', f'job_db = "{workdir / "jobs.db"}"', tail,
                         flags=re.M)
    tail, n_img = re.subn(r'^image_log_dir = ".*"$', f'image_log_dir = "{workdir / "images"}"',
                          tail, flags=re.M)
    assert n_kind == 1 and n_db == 1 and n_img == 1, \
        "sim.toml no longer has [robot] kind / [api] job_db / image_log_dir"
    path = workdir / "sim-page-test.toml"
    path.write_text(without_interfaces(head + tail))
    return path


@contextmanager
def serve_sim_cell(workdir: Path, startup_s: float = 90.0) -> Iterator[str]:
    """``cell serve --config FILE --port N`` on the simulated cell, as an operator starts it.

    Runs in ``workdir`` so its logs stay out of the checkout.
    """
    port = free_port()
    log = (workdir / "cell-serve.log").open("w")
    proc = subprocess.Popen(
        [sys.executable, "-m", "cell", "serve", "--config", str(sim_config(workdir)),
         "--host", "127.0.0.1", "--port", str(port), "--log-level", "warning"],
        cwd=workdir, stdout=log, stderr=subprocess.STDOUT,
        env={**os.environ, "PYTHONPATH": str(REPO)},
    )
    url = f"http://127.0.0.1:{port}"
    try:
        deadline = time.monotonic() + startup_s
        while True:
            if proc.poll() is not None:
                raise RuntimeError(
                    f"cell serve exited with {proc.returncode}:\n"
                    + (workdir / "cell-serve.log").read_text()[-3000:])
            try:
                r = httpx.get(f"{url}/api/v1/health", timeout=1.0)
                if r.status_code == 200 and not still_starting(r.json()):
                    break
            except httpx.HTTPError:
                pass
            if "Traceback" in (workdir / "cell-serve.log").read_text():
                time.sleep(0.5)  # let the rest of the traceback reach the log
                raise RuntimeError("cell serve failed to start:\n"
                                   + (workdir / "cell-serve.log").read_text()[-3000:])
            if time.monotonic() > deadline:
                raise RuntimeError("cell serve did not become healthy in time")
            time.sleep(0.25)
        yield url
    finally:
        proc.terminate()
        try:
            proc.wait(15)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait(5)
        log.close()


# ------------------------------------------------------------------------------------------
# A recording API for page-behaviour tests. It keeps the request/response shapes of the real
# /api/v1 (error envelope, roles, pose JSON) but no robot: each test scripts what it needs and
# then reads back exactly which requests the page sent, and when.

STUB_TOKENS = {"tok-viewer": "viewer", "tok-operator": "operator", "tok-plc": "plc"}


def stub_permissions(role: str) -> frozenset[str]:
    """The real API's permission table, so the stub authorises exactly as the service does."""
    from api.auth import ALWAYS, PERMISSIONS

    return PERMISSIONS.get(role, frozenset()) | ALWAYS  # as api.auth.Caller (anonymous: stop)


@dataclass
class Call:
    method: str
    path: str
    query: str
    body: Any
    t_s: float
    authorization: str = ""  # the Authorization header as sent ("" without one)


@dataclass
class RecordingApi:
    """What the stub received, plus per-route scripted failures ``{path: (status, code, msg)}``."""

    calls: list[Call] = field(default_factory=list)
    failures: dict[str, tuple[int, str, str]] = field(default_factory=dict)
    lock: threading.Lock = field(default_factory=threading.Lock)
    status_extra: dict[str, Any] = field(default_factory=dict)  # merged into GET /status
    robot_extra: dict[str, Any] = field(default_factory=dict)  # merged into its "robot"
    jobs: list[dict[str, Any]] = field(default_factory=list)  # GET /jobs
    frame_headers: dict[str, str] = field(default_factory=dict)  # added to frame.jpg
    recipes: list[dict[str, Any]] = field(default_factory=list)  # GET /recipes
    taught: list[dict[str, Any]] = field(default_factory=list)  # GET /teach
    checks: list[dict[str, Any]] = field(default_factory=list)  # GET /calibration/checks
    anonymous_stop: bool = True  # POST /stop without any token is taken, as the service does
    # tokens POST /stop no longer accepts (as a token revoked between two status polls)
    stop_refuses: set[str] = field(default_factory=set)

    def of(self, path: str) -> list[Call]:
        with self.lock:
            return [c for c in self.calls if c.path == path]


def _error(status: int, code: str, message: str) -> JSONResponse:
    return JSONResponse({"error": {"code": code, "message": message}}, status_code=status)


def _frame_png(n: int) -> bytes:
    img = np.full((200, 320, 3), 40, np.uint8)
    cv2.putText(img, f"frame {n}", (20, 110), cv2.FONT_HERSHEY_SIMPLEX, 1.2, (255, 255, 255), 2)
    ok, buf = cv2.imencode(".png", img)
    assert ok
    return bytes(buf)


def _frame_jpeg(n: int) -> bytes:
    img = cv2.imdecode(np.frombuffer(_frame_png(n), np.uint8), cv2.IMREAD_COLOR)
    ok, buf = cv2.imencode(".jpg", img)
    assert ok
    return bytes(buf)


def recording_app(rec: RecordingApi) -> FastAPI:
    """The stub API plus the real page (``api.http.page.mount_page``).

    Request bodies are parsed with the real ``api.http.schemas`` models, so a page request the
    service would reject as malformed is rejected here too.
    """
    from pydantic import TypeAdapter, ValidationError

    from api.http.page import mount_page
    from api.http.routes.recipes import RecipeApproachRequest
    from api.http.schemas import (
        ApproachRequest,
        GripperRequest,
        JogRequest,
        PickRequest,
        StopRequest,
    )

    app = FastAPI()
    frames = [0]
    need = {
        "/api/v1/jog": "jog", "/api/v1/jog/heartbeat": "jog", "/api/v1/stop": "stop",
        "/api/v1/locate": "locate", "/api/v1/approach": "approach",
        "/api/v1/gripper": "gripper", "/api/v1/arm/home": "operator",
        "/api/v1/arm/unlock": "operator", "/api/v1/pick": "pick",
        "/api/v1/calibration/check": "check_calibration",
        "/api/v1/calibration/reference": "calibrate",
    }
    schemas: dict[str, TypeAdapter[Any]] = {
        "/api/v1/jog": TypeAdapter(JogRequest),
        "/api/v1/approach": TypeAdapter(ApproachRequest),
        "/api/v1/gripper": TypeAdapter(GripperRequest),
        "/api/v1/stop": TypeAdapter(StopRequest),
        "/api/v1/pick": TypeAdapter(PickRequest),
    }
    recipe_schema: TypeAdapter[Any] = TypeAdapter(RecipeApproachRequest)

    @app.middleware("http")
    async def record(request: Request, call_next: Any) -> Any:
        path = request.url.path
        if not path.startswith("/api/v1/"):
            return await call_next(request)
        raw = await request.body()
        body: Any = json.loads(raw) if raw else None
        with rec.lock:
            rec.calls.append(Call(request.method, path, request.url.query, body, time.monotonic(),
                                  request.headers.get("authorization", "")))
        if path == "/api/v1/health":
            return await call_next(request)
        token = request.headers.get("authorization", "").removeprefix("Bearer ")
        refused = path == "/api/v1/stop" and token in rec.stop_refuses
        role = None if refused else STUB_TOKENS.get(token)
        if role is None and path == "/api/v1/stop" and rec.anonymous_stop \
                and "authorization" not in request.headers:
            role = "anonymous"
        if role is None:
            return _error(401, "unauthorized", "unknown token")
        granted = stub_permissions(role) | ({"operator"} if role == "operator" else set())
        recipe_approach = re.fullmatch(r"/api/v1/recipes/[^/]+/approach", path) is not None
        needed = "approach" if recipe_approach else need.get(path, "read")
        if needed not in granted:
            return _error(403, "forbidden", f"role {role!r} may not {needed}")
        schema = recipe_schema if recipe_approach else schemas.get(path)
        if schema is not None and body is not None:
            try:
                schema.validate_python(body)
            except ValidationError as err:
                return _error(422, "invalid_request", str(err))
        if path in rec.failures:
            return _error(*rec.failures[path])
        return await call_next(request)

    @app.get("/api/v1/health")
    def health() -> dict[str, Any]:
        return {"status": "ok", "arm_connected": True, "camera_connected": True}

    @app.get("/api/v1/me")
    def me(request: Request) -> dict[str, Any]:
        role = STUB_TOKENS[request.headers["authorization"].removeprefix("Bearer ")]
        return {"name": role, "role": role, "permissions": sorted(stub_permissions(role))}

    @app.get("/api/v1/status")
    def status() -> dict[str, Any]:
        return {
            "state": "idle",
            "robot": {"connected": True, "mode": "RUNNING", "safety": "NORMAL",
                      "moving": False, "protective_stop": False,
                      "T_base_tcp": {"position_mm": [-480.0, -100.0, 400.0],
                                     "rotvec_rad": [3.14159, 0.0, 0.0]},
                      **rec.robot_extra},
            "camera": {"connected": True, "last_frame_age_s": 0.05},
            "gripper": {"activated": True, "position_mm": 85.0, "object_detected": False,
                        "moving": False, "fault": ""},
            "job": None,
            "last_locate": {"quality": {"rms_px": 0.21, "ambiguous": False,
                                        "frame_age_s": 1.5}},
            **rec.status_extra,
        }

    @app.get("/api/v1/camera/frame.png")
    def frame() -> Response:
        frames[0] += 1
        return Response(_frame_png(frames[0]), media_type="image/png",
                        headers={"X-Frame-Age-S": "0.040"})

    @app.get("/api/v1/camera/frame.jpg")
    def frame_jpg() -> Response:
        frames[0] += 1
        return Response(_frame_jpeg(frames[0]), media_type="image/jpeg",
                        headers={"X-Frame-Age-S": "0.040", **rec.frame_headers})

    @app.get("/api/v1/alarms")
    def alarms() -> dict[str, Any]:
        return {"alarms": [], "active": 0, "total": 0, "offset": 0}

    @app.get("/api/v1/jobs")
    def jobs() -> dict[str, Any]:
        return {"jobs": rec.jobs, "total": len(rec.jobs), "offset": 0}

    @app.get("/api/v1/jobs/{job_id}")
    def job(job_id: str) -> Any:
        found = [j for j in rec.jobs if j["id"] == job_id]
        return found[0] if found else _error(404, "not_found", f"no job {job_id}")

    @app.get("/api/v1/teach")
    def taught() -> dict[str, Any]:
        return {"taught": rec.taught}

    @app.get("/api/v1/recipes")
    def recipes() -> dict[str, Any]:
        return {"recipes": rec.recipes}

    @app.post("/api/v1/recipes/{ref}/approach")
    async def recipe_approach(ref: str, request: Request) -> Any:
        body = RecipeApproachRequest.model_validate(await request.json())
        found = [r for r in rec.recipes if ref in (r["name"], str(r["number"]))]
        if not found:
            return _error(404, "recipe_not_found", f"no recipe {ref!r}")
        r = found[0]
        record = {"name": r["name"], "number": r["number"], "version": r["version"],
                  "target": body.target or r["targets"][0]["name"]}
        return {"id": "4ec1be00", "kind": "approach", "state": "running",
                "params": {"recipe": record}, "progress": {}, "result": None, "error": None}

    @app.get("/api/v1/camera/settings")
    def camera_settings() -> dict[str, Any]:
        return {"exposure_us": 4000, "iso": 100, "focus": None}

    @app.get("/api/v1/images")
    def images() -> dict[str, Any]:
        return {"images": [], "total": 0, "offset": 0, "enabled": False}

    for p in ("/api/v1/jog", "/api/v1/jog/heartbeat", "/api/v1/stop", "/api/v1/gripper",
              "/api/v1/arm/unlock"):
        app.post(p)(lambda: {"ok": True})

    @app.post("/api/v1/arm/home")
    def home() -> dict[str, Any]:
        return {"id": "home0001", "kind": "home", "state": "running", "progress": {},
                "result": None, "error": None}

    @app.post("/api/v1/locate")
    def locate() -> dict[str, Any]:
        return {"T_base_target": {"position_mm": [-480.0, -100.0, 0.0],
                                  "rotvec_rad": [3.14159, 0.0, 0.0]},
                "quality": {"rms_px": 0.2, "ambiguous": False, "frame_age_s": 0.03}}

    @app.post("/api/v1/approach")
    def approach() -> dict[str, Any]:
        return {"id": "0123abcd", "kind": "approach", "state": "running",
                "progress": {}, "result": None, "error": None}

    @app.get("/api/v1/calibration/checks")
    def calibration_checks() -> dict[str, Any]:
        return {"jobs": rec.checks, "total": None, "offset": 0}

    @app.post("/api/v1/calibration/check")
    def check() -> dict[str, Any]:
        return {"id": "c4ec0001", "kind": "calibration_check", "state": "running",
                "params": {}, "progress": {}, "result": None, "error": None}

    @app.post("/api/v1/calibration/reference")
    def reference() -> dict[str, Any]:
        return {"id": "4ef00001", "kind": "calibration_reference", "state": "running",
                "params": {}, "progress": {}, "result": None, "error": None}

    @app.post("/api/v1/pick")
    def pick() -> dict[str, Any]:
        return {"id": "91c4ab00", "kind": "pick", "state": "running",
                "progress": {}, "result": None, "error": None}

    mount_page(app)
    return app
