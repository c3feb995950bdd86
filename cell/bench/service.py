"""``cell bench service``: the simulated cell service under the load an operator floor gives it.

What runs: ``cell serve`` on the built-in simulated cell (its own loopback address and port,
its own job database), then

1. idle: nobody connected for ``idle_s``; CPU time of the service, the ur_rtde client child
   and the simulated controller, read from ``/proc`` (percent of one core);
2. load for ``duration_s``: ``pollers`` clients polling ``GET /status`` every 250 ms (as the
   operator page does), ``streams`` clients reading ``GET /events``, ``viewers`` clients
   showing the live view as the page does (``/camera/frame.jpg?overlay=true`` every 150 ms;
   ``viewer_image="png"``: the full-size ``frame.png``, encoded per request, as runs before
   2026-12-01 23:30 did) (one process for each kind; aiohttp clients, one connection each,
   as separate browsers; httpx, used before 2026-12-02 02:00, cost the host 3-4x the CPU per
   request, 50 % of a core for the pollers alone, and its own delays were measured as the
   service's), while
   this process starts a continuous jog, lets the arm move for ``move_s`` and sends
   ``POST /api/v1/stop``, at least ``min_stops`` times.

STOP latency is measured from the moment the request is sent to the moment the cell handed
the stop to the arm adapter (``commanded_monotonic_s`` in the answer; ``time.monotonic`` is
one clock for every process on the host); ``stop_adapter_ms_*`` is how long the adapter's stop
calls took (ur_rtde's speedStop and stopL, each acknowledged by the control script), and
``stop_http_ms_*`` the whole round trip. Every number depends on what else the host runs:
the report carries the host's load average before and after.
"""

from __future__ import annotations

import contextlib
import json
import multiprocessing as mp
import os
import re
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Iterator
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import httpx  # the STOP sender: one synchronous client
import numpy as np

SERVICE_NICE = -5  # the systemd unit's Nice= (the bench serves the cell as it is deployed)
STATUS_PERIOD_S = 0.25  # the operator page's status poll
VIEWER_MIN_PERIOD_S = 0.15  # the operator page's camera loop
LAG_PROBE_S = 0.005  # the load processes' event-loop lag probe
OPERATOR = {"Authorization": "Bearer sim-operator"}
VIEWER = {"Authorization": "Bearer sim-viewer"}


@dataclass(frozen=True)
class ServiceBenchConfig:
    duration_s: float = 20.0
    idle_s: float = 5.0
    pollers: int = 50
    streams: int = 10
    viewers: int = 2
    min_stops: int = 100
    move_s: float = 0.08
    viewer_image: str = "jpg"  # "jpg": the page's shared live view; "png": a still per request
    poller_processes: int = 2  # the pollers' HTTP clients cost more CPU than the service does
    # set per load process: its first poller and the pollers of all, for the poll phases
    poller_first: int = 0
    poller_phase_of: int = 0
    # the service's nice value, as cell/deploy/ur-vision-cell.service runs it (Nice=-5);
    # applied when the host allows it (root or CAP_SYS_NICE), None: as inherited
    service_nice: int | None = SERVICE_NICE


# -- /proc ---------------------------------------------------------------------------------

def _cpu_ticks(pid: int) -> int | None:
    """utime + stime of a process (clock ticks), None when it is gone."""
    try:
        with open(f"/proc/{pid}/stat") as f:
            fields = f.read().rsplit(")", 1)[1].split()
    except OSError:
        return None
    return int(fields[11]) + int(fields[12])  # fields 14 and 15 of proc(5)


def _children(pid: int) -> list[tuple[int, str]]:
    """(pid, command line) of the direct children of ``pid``."""
    out = []
    for entry in os.listdir("/proc"):
        if not entry.isdigit():
            continue
        try:
            with open(f"/proc/{entry}/stat") as f:
                ppid = int(f.read().rsplit(")", 1)[1].split()[1])
            if ppid != pid:
                continue
            with open(f"/proc/{entry}/cmdline", "rb") as f:
                cmd = f.read().replace(b"\0", b" ").decode("utf-8", "replace")
        except (OSError, ValueError, IndexError):
            continue
        out.append((int(entry), cmd))
    return out


def service_processes(pid: int) -> dict[str, int]:
    """The service's processes by role: service, ur_client, controller."""
    procs = {"service": pid}
    for child, cmd in _children(pid):
        if "drivers.ur.client_process" in cmd:
            procs["ur_client"] = child
        elif "ur_controller" in cmd:
            procs["controller"] = child
    return procs


def cpu_percent(pids: dict[str, int], seconds: float) -> dict[str, float | None]:
    """Percent of one core each process used over the next ``seconds``."""
    hz = os.sysconf("SC_CLK_TCK")
    t0, before = time.monotonic(), {k: _cpu_ticks(p) for k, p in pids.items()}
    time.sleep(seconds)
    t1, after = time.monotonic(), {k: _cpu_ticks(p) for k, p in pids.items()}
    out: dict[str, float | None] = {}
    for k in pids:
        b, a = before[k], after[k]
        out[k] = None if a is None or b is None else round(100.0 * (a - b) / hz / (t1 - t0), 1)
    return out


# -- the service ------------------------------------------------------------------------------

def _free_port(host: str) -> int:
    with socket.socket() as s:
        s.bind((host, 0))
        return int(s.getsockname()[1])


def _config_text(host: str, state_dir: Path) -> str:
    """The built-in simulated cell on its own controller address and state directory."""
    from cell.configs import __file__ as configs_init

    text = (Path(configs_init).parent / "sim.toml").read_text()
    text = re.sub(r'(?m)^host = ".*"$', f'host = "{host}"', text)
    text = re.sub(r'(?m)^job_db = ".*"$', f'job_db = "{state_dir / "jobs.db"}"', text)
    return re.sub(r'(?m)^calibration_dir = "[^"]*"',
                  f'calibration_dir = "{state_dir / "calibration"}"', text)


@contextlib.contextmanager
def serving(timeout_s: float = 90.0, nice: int | None = None, stop_log: Path | None = None,
            extra_args: list[str] | None = None, log_path: Path | None = None
            ) -> Iterator[tuple[str, subprocess.Popen[bytes]]]:
    """``cell serve`` on a free loopback address; yields (base URL, process). With
    ``stop_log`` the simulated controller appends each stop command's receive time there;
    ``extra_args`` go to ``cell serve`` (e.g. ``--modbus-port N``); ``log_path``: its
    warnings and errors go there and are kept (else to the temporary state directory), and
    the stacks it wrote when it stood still (``stall-traces.txt``) are kept beside it as
    ``<log_path>.stall-traces.txt``: the state directory goes when the bench ends."""
    from cell.runtime import STALL_TRACES_FILE
    from fakes.ur_controller.process import free_loopback_host
    from fakes.ur_controller.script import STOP_LOG_ENV

    host = free_loopback_host()
    port = _free_port(host)
    with tempfile.TemporaryDirectory(prefix="cell-bench-") as tmp:
        cfg = Path(tmp) / "cell.toml"
        cfg.write_text(_config_text(host, Path(tmp)))
        env = dict(os.environ)
        if stop_log is not None:  # the simulated controller notes each stop's arrival here
            env[STOP_LOG_ENV] = str(stop_log)
        log = log_path if log_path is not None else Path(tmp) / "serve.log"
        proc = subprocess.Popen(
            [sys.executable, "-m", "cell", "serve", "--config", str(cfg), "--host", host,
             "--port", str(port), "--log-level", "warning",
             *(["--log-format", "json"] if log_path is not None else []),  # timed lines
             *(extra_args or [])], env=env,
            stdout=subprocess.DEVNULL, stderr=open(log, "wb"))  # noqa: SIM115
        if nice is not None:  # before it starts its own processes, which inherit it
            with contextlib.suppress(PermissionError):
                os.setpriority(os.PRIO_PROCESS, proc.pid, nice)
        base = f"http://{host}:{port}"
        try:
            deadline = time.monotonic() + timeout_s
            while True:
                if proc.poll() is not None:
                    raise RuntimeError("cell serve exited: " + log.read_text()[-2000:])
                with contextlib.suppress(httpx.HTTPError):
                    r = httpx.get(f"{base}/api/v1/health", timeout=2.0)
                    if r.status_code == 200 and r.json().get("status") == "ok":
                        break
                if time.monotonic() > deadline:
                    raise RuntimeError("cell serve did not become healthy in time")
                time.sleep(0.2)
            yield base, proc
        finally:
            proc.send_signal(signal.SIGTERM)
            try:
                proc.wait(timeout=15.0)
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait()
            traces = Path(tmp) / STALL_TRACES_FILE
            if log_path is not None and traces.exists():
                shutil.copyfile(traces, log_path.with_name(log_path.name + ".stall-traces.txt"))


# -- the load (in its own process) ----------------------------------------------------------------

def _load_main(base: str, cfg: ServiceBenchConfig, start_s: float, end_s: float,
               out: mp.Queue[dict[str, Any]]) -> None:
    import asyncio

    import aiohttp

    status_ms: list[float] = []
    gaps_ms: list[float] = []
    publish_gaps_ms: list[float] = []  # between the server's publish times of the same events
    frames = [0]
    events = [0]
    errors: list[str] = []
    lag_ms: list[float] = []  # how late this process's own event loop woke (client-side delay)

    async def lag_meter() -> None:
        while time.monotonic() < end_s:
            t0 = time.monotonic()
            await asyncio.sleep(LAG_PROBE_S)
            if t0 >= start_s:
                lag_ms.append(1000.0 * (time.monotonic() - t0 - LAG_PROBE_S))

    total_pollers = cfg.poller_phase_of or cfg.pollers

    async def poller(client: aiohttp.ClientSession, i: int) -> None:
        await asyncio.sleep(STATUS_PERIOD_S * (cfg.poller_first + i) / max(1, total_pollers))
        while time.monotonic() < end_s:
            t0 = time.monotonic()
            try:
                async with client.get(f"{base}/api/v1/status", headers=VIEWER) as r:
                    body = await r.read()
                    if r.status != 200:
                        errors.append(f"status {r.status}")
                    else:
                        json.loads(body)
            except (aiohttp.ClientError, TimeoutError) as err:
                errors.append(f"status: {err!r}")
            t1 = time.monotonic()
            if t0 >= start_s:
                status_ms.append(1000.0 * (t1 - t0))
            await asyncio.sleep(max(0.0, STATUS_PERIOD_S - (t1 - t0)))

    async def stream(client: aiohttp.ClientSession) -> None:
        last: float | None = None
        last_published: float | None = None
        is_state = False
        try:
            async with client.get(f"{base}/api/v1/events", headers=VIEWER) as r:
                if r.status != 200:
                    errors.append(f"events {r.status}")
                    return
                async for raw in r.content:
                    line = raw.decode().rstrip("\r\n")
                    now = time.monotonic()
                    if now >= end_s:
                        break
                    if is_state and line.startswith("data: "):
                        is_state = False
                        published = float(json.loads(line[6:])["time"])
                        if last_published is not None and now >= start_s:
                            publish_gaps_ms.append(1000.0 * (published - last_published))
                        last_published = published
                    if line != "event: state":
                        continue
                    is_state = True
                    events[0] += 1
                    if last is not None and last >= start_s:
                        gaps_ms.append(1000.0 * (now - last))
                    last = now
        except (aiohttp.ClientError, TimeoutError, ValueError) as err:  # ValueError: a
            errors.append(f"events: {err!r}")  # line longer than aiohttp's read limit

    async def viewer(client: aiohttp.ClientSession) -> None:
        while time.monotonic() < end_s:
            t0 = time.monotonic()
            try:
                async with client.get(f"{base}/api/v1/camera/frame.{cfg.viewer_image}",
                                      params={"overlay": "true"}, headers=VIEWER) as r:
                    await r.read()
                    if r.status != 200:
                        errors.append(f"frame {r.status}")
                    elif t0 >= start_s:
                        frames[0] += 1
            except (aiohttp.ClientError, TimeoutError) as err:
                errors.append(f"frame: {err!r}")
            await asyncio.sleep(max(0.0, VIEWER_MIN_PERIOD_S - (time.monotonic() - t0)))

    async def main() -> None:
        # one session (one connection) each, as separate browsers would be
        n = cfg.streams + cfg.viewers + cfg.pollers
        timeout = aiohttp.ClientTimeout(total=None, sock_read=10.0, sock_connect=10.0)
        clients = [aiohttp.ClientSession(timeout=timeout,
                                         connector=aiohttp.TCPConnector(limit=1))
                   for _ in range(n)]
        try:
            it = iter(clients)
            await asyncio.gather(
                lag_meter(),
                *(stream(next(it)) for _ in range(cfg.streams)),
                *(viewer(next(it)) for _ in range(cfg.viewers)),
                *(poller(next(it), i) for i in range(cfg.pollers)))
        finally:
            for c in clients:
                await c.close()

    asyncio.run(main())
    role = "pollers" if cfg.pollers else "streams" if cfg.streams else "viewers"
    out.put({"status_ms": status_ms, "gaps_ms": gaps_ms, "publish_gaps_ms": publish_gaps_ms,
             f"{role}_lag_ms": lag_ms,
             "frames": frames[0],
             "events": events[0], "errors": errors})


# -- STOP with an arm moving -------------------------------------------------------------------

STOP_RECEIPT_WAIT_S = 1.0  # a stop the controller has not received by then failed


def controller_receipts(stop_log: Path | None) -> list[float]:
    """The controller's receive times of stop commands so far (host monotonic seconds)."""
    if stop_log is None or not stop_log.exists():
        return []
    return [float(line.split()[0]) for line in stop_log.read_text().splitlines()
            if line.strip()]


def to_controller_ms(sent_s: float, stop_log: Path | None) -> float | None:
    """From a stop's send to the controller's first receipt of a stop command after it;
    None when none arrived within STOP_RECEIPT_WAIT_S (a failed stop)."""
    deadline = time.monotonic() + STOP_RECEIPT_WAIT_S
    while True:
        after = [t for t in controller_receipts(stop_log) if t >= sent_s]
        if after:
            return 1000.0 * (min(after) - sent_s)
        if time.monotonic() > deadline:
            return None
        time.sleep(0.005)


def _stops(base: str, cfg: ServiceBenchConfig, start_s: float, end_s: float,
           stop_log: Path | None = None, to_controller: list[float] | None = None,
           ) -> tuple[list[float], list[float], list[float], list[str], int]:
    """Jog, stop, repeat; (stop ms, adapter ms, round-trip ms, errors, stops with the arm
    moving). With ``stop_log``, each stop's time to the controller goes to ``to_controller``
    (infinite when it never arrived)."""
    stop_ms: list[float] = []
    adapter_ms: list[float] = []
    http_ms: list[float] = []
    errors: list[str] = []
    moving_at_stop = 0
    sign = 1.0
    with httpx.Client(timeout=httpx.Timeout(10.0)) as client:
        while time.monotonic() < start_s:
            time.sleep(0.01)
        while len(stop_ms) < cfg.min_stops or time.monotonic() < end_s:
            if time.monotonic() > end_s + 60.0:
                errors.append("stops: not enough stops within a minute past the load")
                break
            r = client.post(f"{base}/api/v1/jog", headers=OPERATOR, json={
                "mode": "continuous", "linear_mm_s": [40.0 * sign, 0.0, 0.0]})
            if r.status_code == 409:  # the last jog is still settling: try again shortly
                time.sleep(0.01)
                continue
            if r.status_code != 200:
                errors.append(f"jog {r.status_code}: {r.text[:200]}")
                time.sleep(0.1)
                continue
            sign = -sign
            time.sleep(cfg.move_s)
            t0 = time.monotonic()
            r = client.post(f"{base}/api/v1/stop", headers=OPERATOR,
                            json={"reason": "bench"})
            t1 = time.monotonic()
            if stop_log is not None and to_controller is not None:
                ms = to_controller_ms(t0, stop_log)
                to_controller.append(float("inf") if ms is None else ms)
            if r.status_code != 200:
                errors.append(f"stop {r.status_code}: {r.text[:200]}")
                continue
            body = r.json()
            commanded = body.get("commanded_monotonic_s")
            if commanded is None:
                errors.append("stop: no commanded_monotonic_s in the answer")
                continue
            if body.get("cancelled") == "jog":
                moving_at_stop += 1
            stop_ms.append(1000.0 * (float(commanded) - t0))
            if body.get("sent_monotonic_s") is not None:
                adapter_ms.append(1000.0 * (float(body["sent_monotonic_s"]) - float(commanded)))
            http_ms.append(1000.0 * (t1 - t0))
    return stop_ms, adapter_ms, http_ms, errors, moving_at_stop


def _pct_failed(values: list[float], q: float) -> float | None:
    """A percentile where a failed stop (inf) counts as the slowest; None when it is one."""
    if not values:
        return None
    v = float(np.percentile(values, q, method="higher"))
    return None if v == float("inf") else round(v, 1)


def _pct(values: list[float], q: float) -> float | None:
    return None if not values else round(float(np.percentile(values, q)), 1)


def run_service_bench(cfg: ServiceBenchConfig | None = None) -> dict[str, Any]:
    cfg = cfg or ServiceBenchConfig()
    loadavg_before = round(os.getloadavg()[0], 2)  # other work on the host skews every number
    stop_dir = tempfile.TemporaryDirectory(prefix="cell-bench-stops-")
    stop_log = Path(stop_dir.name) / "stops.log"
    to_controller: list[float] = []
    with stop_dir, serving(nice=cfg.service_nice, stop_log=stop_log) as (base, proc):
        time.sleep(2.0)  # let the start settle (kernels, first frames, gripper activation)
        pids = service_processes(proc.pid)
        nices: dict[str, int] = {}
        for name, pid in pids.items():
            with contextlib.suppress(OSError):
                nices[name] = os.getpriority(os.PRIO_PROCESS, pid)
        idle = cpu_percent(pids, cfg.idle_s)
        start_s = time.monotonic() + 2.0  # the load's clients connect first
        end_s = start_s + cfg.duration_s
        ctx = mp.get_context("spawn")
        queue: mp.Queue[dict[str, Any]] = ctx.Queue()
        # one process per kind of client, so a live view's megabyte frames do not hold up
        # the status pollers' own event loop (that would be measured as status latency)
        n_proc = max(1, min(cfg.poller_processes, cfg.pollers))
        split = [cfg.pollers * k // n_proc for k in range(n_proc + 1)]
        roles = [*(replace(cfg, streams=0, viewers=0, pollers=split[k + 1] - split[k],
                           poller_first=split[k], poller_phase_of=cfg.pollers)
                   for k in range(n_proc)),
                 replace(cfg, pollers=0, viewers=0), replace(cfg, pollers=0, streams=0)]
        names = [*(f"pollers{k}" for k in range(n_proc)), "streams", "viewers"]
        loads = [ctx.Process(target=_load_main, args=(base, role, start_s, end_s, queue),
                             daemon=True) for role in roles]
        for load in loads:
            load.start()
        loaded: dict[str, Any] = {"status_ms": [], "gaps_ms": [], "publish_gaps_ms": [],
                                  "pollers_lag_ms": [], "streams_lag_ms": [],
                                  "viewers_lag_ms": [], "frames": 0, "events": 0, "errors": []}
        cpu_load: dict[str, float | None] = {}

        def measure_load_cpu() -> None:
            while time.monotonic() < start_s:
                time.sleep(0.01)
            clients = {f"bench_{name}": load.pid for name, load in zip(names, loads, strict=True)
                       if load.pid is not None}
            used = cpu_percent({**pids, **clients}, max(1.0, cfg.duration_s - 1.0))
            pollers = [v for k, v in used.items() if k.startswith("bench_pollers")]
            cpu_load.update({k: v for k, v in used.items() if not k.startswith("bench_pollers")})
            cpu_load["bench_pollers"] = None if None in pollers else round(
                sum(v for v in pollers if v is not None), 1)

        meter = threading.Thread(target=measure_load_cpu, daemon=True)
        meter.start()
        stop_ms, adapter_ms, http_ms, errors, moving = _stops(base, cfg, start_s, end_s,
                                                        stop_log, to_controller)
        try:
            for _ in loads:
                part = queue.get(timeout=cfg.duration_s + 60.0)
                for key, value in part.items():
                    loaded[key] = loaded[key] + value
        except Exception as err:
            errors.append(f"load process: {err!r}")
        for load in loads:
            load.join(timeout=10.0)
        meter.join(timeout=cfg.duration_s + 5.0)
        health = httpx.get(f"{base}/api/v1/health", timeout=5.0).json()
    errors += loaded.get("errors", [])
    gaps = loaded.get("gaps_ms", [])
    idle_total = sum(v for k, v in idle.items() if k in ("service", "ur_client") and v)
    reached = [ms for ms in to_controller if ms != float("inf")]
    report: dict[str, Any] = {
        # the least kind figure first: send -> the controller has the stop (failed: never)
        "stop_to_controller_ms_p99": _pct_failed(to_controller, 99),
        "stop_to_controller_ms_p50": _pct_failed(to_controller, 50),
        "stop_to_controller_ms_max": _pct_failed(to_controller, 100),
        "stop_to_controller_failed": len(to_controller) - len(reached),
        "stop_ms_p50": _pct(stop_ms, 50), "stop_ms_p99": _pct(stop_ms, 99),
        "stop_ms_max": _pct(stop_ms, 100),
        "stop_adapter_ms_p50": _pct(adapter_ms, 50), "stop_adapter_ms_p99": _pct(adapter_ms, 99),
        "stop_http_ms_p50": _pct(http_ms, 50), "stop_http_ms_p99": _pct(http_ms, 99),
        "stops": len(stop_ms), "stops_while_jogging": moving,
        "status_ms_p50": _pct(loaded.get("status_ms", []), 50),
        "status_ms_p99": _pct(loaded.get("status_ms", []), 99),
        "status_polls": len(loaded.get("status_ms", [])),
        "sse_gap_ms_max": None if not gaps else round(max(gaps), 1),
        "sse_gap_ms_p99": _pct(gaps, 99),
        "sse_publish_gap_ms_max": _pct(loaded.get("publish_gaps_ms", []), 100),
        "sse_state_events": loaded.get("events", 0),
        # the load's own event loops: how late they woke; a status or SSE delay this large
        # was spent in the (starved) client, not in the service
        "client_loop_lag_ms_p99": {role: _pct(loaded.get(f"{role}_lag_ms", []), 99)
                                   for role in ("pollers", "streams", "viewers")},
        "frames_viewed": loaded.get("frames", 0),
        "idle_cpu_pct": idle,
        "idle_cpu_pct_service_plus_ur_client": round(idle_total, 1),
        "load_cpu_pct": cpu_load,
        "errors": len(errors),
        "error_samples": errors[:10],
        "health_after": health.get("status"),
        "nice": nices,  # each process's nice value (the service's as the unit sets it)
        "load": {"duration_s": cfg.duration_s, "pollers": cfg.pollers,
                 "status_period_s": STATUS_PERIOD_S, "streams": cfg.streams,
                 "viewers": cfg.viewers, "viewer_image": cfg.viewer_image,
                 "cores": os.cpu_count(),
                 "host_loadavg_1min_before": loadavg_before,
                 "host_loadavg_1min_after": round(os.getloadavg()[0], 2)},
    }
    return report


def format_report(r: dict[str, Any]) -> str:
    idle = ", ".join(f"{k} {v}%" for k, v in r["idle_cpu_pct"].items())
    load = ", ".join(f"{k} {v}%" for k, v in r["load_cpu_pct"].items())
    lo = r["load"]
    return "\n".join([
        f"load: {lo['pollers']} status pollers every {lo['status_period_s']} s, "
        f"{lo['streams']} SSE streams, {lo['viewers']} live views, {lo['duration_s']} s, "
        f"{lo['cores']} cores, host load average {lo['host_loadavg_1min_before']} before, "
        f"{lo['host_loadavg_1min_after']} after; nice "
        + ", ".join(f"{k} {v}" for k, v in r["nice"].items()),
        f"stop (send -> controller has it): p99 {r['stop_to_controller_ms_p99']} ms, p50 "
        f"{r['stop_to_controller_ms_p50']} ms, {r['stop_to_controller_failed']} failed\n"
        f"stop (request -> arm commanded): p50 {r['stop_ms_p50']} ms, p99 {r['stop_ms_p99']} ms,"
        f" max {r['stop_ms_max']} ms over {r['stops']} stops "
        f"({r['stops_while_jogging']} while jogging); the adapter's stop calls p50 "
        f"{r['stop_adapter_ms_p50']} ms, p99 {r['stop_adapter_ms_p99']} ms; round trip p99 "
        f"{r['stop_http_ms_p99']} ms",
        f"status: p50 {r['status_ms_p50']} ms, p99 {r['status_ms_p99']} ms "
        f"({r['status_polls']} polls)",
        f"SSE state events: max gap {r['sse_gap_ms_max']} ms, p99 {r['sse_gap_ms_p99']} ms "
        f"({r['sse_state_events']} events; max gap between their publish times "
        f"{r['sse_publish_gap_ms_max']} ms)",
        f"idle CPU (% of one core): {idle}; service + ur_client "
        f"{r['idle_cpu_pct_service_plus_ur_client']}%",
        f"CPU under load: {load}",
        f"errors: {r['errors']}" + (f" ({'; '.join(r['error_samples'])})"
                                     if r["errors"] else ""),
    ])

