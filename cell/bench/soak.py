"""``cell bench soak``: production cycles against the simulated cell service for minutes on
end, and how its memory, file descriptors, threads and job database grow.

    cell bench soak [--minutes 15] [--json]

What runs: ``cell serve`` on the built-in simulated cell (as ``cell bench service`` serves it:
at the systemd unit's nice value, -5, where the host allows it; its own loopback address, port
and job database; the OPC UA, XML-RPC and Modbus servers off
unless ``--interfaces``, their fixed ports would collide with another service on the host),
then, until the time is up:

- the production cycle, one after another: home, locate, look-and-move approach, gripper
  close and open; every 5th cycle also a servo approach and a 5 s conveyor track (all
  through the HTTP API with ``wait=true``, as a PLC's script does);
- ``GET /status`` and the live view ``GET /camera/frame.jpg?overlay=true`` polled at ~7 Hz
  each, one ``GET /events`` stream open, and an RTDE reader of its own on the simulated
  controller (ur_rtde's RTDEReceiveInterface, as a second client on a real cell would be),
  which notes every stretch of 0.5 s or more in which the controller's timestamp stood still.

These clients run at the service's nice value too (where the host allows it): they stand for
other machines, which CPU burners on the cell PC do not slow. With ``--service-log FILE`` the
service's warnings are kept, one JSON object a line with its time, to read beside the
report's ``failures`` (each with the time into the run it happened).

Sampled every ``SAMPLE_S`` from ``/proc`` (no psutil): VmRSS of the service and of its ur_rtde
child, their open fds and threads, and the job database's size (with its WAL). Reported per
minute and in total, with a least-squares line through each series (``numpy.polyfit``):
``service_rss_mb_per_h`` is the RSS slope after the first 10 % of the run (start-up caches
and the first frames' buffers fill then). A cycle fails when a step answers an error or its
job does not succeed; failures are counted per minute with their error codes. Every number
depends on what else the host runs: the report carries the host's load average.

A failure is the host's when its message says the host held the whole service still, or when
it came after a *blocked* stall (a thread held the interpreter and did not run) and, between
the step's start and the failure, :mod:`cell.bench.kernel_waits` found a thread of the service
waiting in the kernel (state D) in every 0.1 s sample of a stretch at least
``KERNEL_WAIT_SHARE`` of that stall long; each such failure lists the kernel functions waited
in. Judged when the failure is seen, from the full message.
"""

from __future__ import annotations

import contextlib
import os
import re
import threading
import time
from collections import Counter
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any
from urllib.parse import urlparse

import httpx
import numpy as np

from cell.bench.kernel_waits import KernelWaits, WaitRun
from cell.bench.service import SERVICE_NICE, service_processes, serving
from cell.supervision.host_watch import (
    BLOCKED_STALL_MARK,
    HOST_STALL_MARK,
    KINDS,
    OWN_STALL_MARK,
)

OPERATOR = {"Authorization": "Bearer sim-operator"}
VIEWER = {"Authorization": "Bearer sim-viewer"}
POLL_PERIOD_S = 1.0 / 7.0  # status and the live frame, each
FOLLOW_S = 120.0  # a job still running when its wait answered is followed this long
SAMPLE_S = 5.0  # /proc samples
SERVO_EVERY = 5  # every 5th cycle: a servo approach and a track
STREAM_GAP_S = 0.5  # the controller's RTDE timestamp standing still this long is a gap
TRACK_S = 5.0
JOB_KINDS = ("home", "locate", "approach_look_and_move", "gripper_close", "gripper_open",
             "approach_servo", "track")
Progress = Callable[[str, int, int], None]


# -- /proc -------------------------------------------------------------------------------------

def rss_mb(pid: int) -> float | None:
    """VmRSS of a process in MB, None when it is gone."""
    try:
        for line in Path(f"/proc/{pid}/status").read_text().splitlines():
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) / 1024.0
    except (OSError, ValueError):
        return None
    return None


def _count(path: str) -> int | None:
    try:
        return len(os.listdir(path))
    except OSError:
        return None


def fds(pid: int) -> int | None:
    return _count(f"/proc/{pid}/fd")


def threads(pid: int) -> int | None:
    return _count(f"/proc/{pid}/task")


def _db_kb(db: Path) -> float:
    total = 0
    for suffix in ("", "-wal", "-shm"):
        with contextlib.suppress(OSError):
            total += (db.parent / (db.name + suffix)).stat().st_size
    return total / 1024.0


def _job_db(pid: int) -> Path | None:
    """The service's job database: beside the config ``serving`` wrote (its ``job_db``)."""
    try:
        argv = Path(f"/proc/{pid}/cmdline").read_bytes().split(b"\0")
    except OSError:
        return None
    args = [a.decode() for a in argv]
    if "--config" not in args:
        return None
    return Path(args[args.index("--config") + 1]).parent / "jobs.db"


# -- statistics ----------------------------------------------------------------------------------

def _pct(values: list[float], q: float) -> float | None:
    return None if not values else round(float(np.percentile(values, q)), 1)


def slope_per_h(t_s: Sequence[float], values: Sequence[float | None], skip: float = 0.0
                ) -> float | None:
    """Least-squares slope of ``values`` over time, per hour, after the first ``skip`` of the
    run (a fraction); None with fewer than 3 samples."""
    if not t_s:
        return None
    t0 = t_s[0] + skip * (t_s[-1] - t_s[0])
    pts = [(t, v) for t, v in zip(t_s, values, strict=True) if t >= t0 and v is not None]
    if len(pts) < 3:
        return None
    t, v = np.array(pts, dtype=float).T
    return round(float(np.polyfit(t / 3600.0, v, 1)[0]), 1)


# -- the load ------------------------------------------------------------------------------------

class _Soak:
    """What the clients record, under one lock; every entry is (monotonic s, ...)."""

    def __init__(self) -> None:
        self.lock = threading.Lock()
        self.stop = threading.Event()
        self.latency: dict[str, list[tuple[float, float]]] = {"status": [], "frame": []}
        self.jobs: dict[str, list[tuple[float, float]]] = {k: [] for k in JOB_KINDS}
        self.cycles: list[tuple[float, str | None]] = []  # (end, error code or None)
        self.poll_errors: Counter[str] = Counter()
        self.events = 0
        self.rtde_reads = 0
        self.rtde_errors: Counter[str] = Counter()
        self.error_messages: list[str] = []
        # (when, code, message, the kernel-wait stretch of a failure after a blocked stall)
        self.failures: list[tuple[float, str, str, WaitRun | None]] = []
        self.waits: KernelWaits | None = None
        # (when the stream moved again, how long its timestamp stood, how late the reader
        # itself woke at worst meanwhile): a gap the reader was awake for is the controller's
        self.stream_gaps: list[tuple[float, float, float]] = []
        self.poll_timeouts: list[tuple[float, str]] = []

    def note(self, series: dict[str, list[tuple[float, float]]], key: str, t0: float) -> None:
        now = time.monotonic()
        with self.lock:
            series[key].append((now, 1000.0 * (now - t0)))


    def failed(self, kind: str, code: str, message: str, since_s: float) -> None:
        """A step begun at ``since_s`` (monotonic) failed with ``message`` (whole: the host
        watch's note comes last)."""
        now = time.monotonic()
        run = None if self.waits is None else kernel_wait(since_s, now, message, self.waits)
        with self.lock:
            self.failures.append((now, f"{kind}:{code}", message, run))
            if len(self.error_messages) < 10:
                self.error_messages.append(message[:200])


class StepFailed(Exception):
    def __init__(self, code: str) -> None:
        super().__init__(code)
        self.code = code


def _code(r: httpx.Response, messages: list[str] | None = None) -> str:
    """The error code of a refused request (``{"error": {"code": ...}}``), else its status;
    its message goes to ``messages`` (the first ten)."""
    with contextlib.suppress(ValueError, AttributeError, KeyError, TypeError):
        error = r.json()["error"]
        if messages is not None and len(messages) < 10:
            messages.append(str(error.get("message", "")))
        return str(error["code"])
    return f"http_{r.status_code}"


def _step(soak: _Soak, client: httpx.Client, kind: str, path: str, body: dict[str, Any]
          ) -> None:
    t0 = time.monotonic()
    try:
        r = client.post(path, json=body, headers=OPERATOR)
    except httpx.HTTPError as err:
        soak.failed(kind, type(err).__name__, str(err), t0)
        raise StepFailed(f"{kind}:{type(err).__name__}") from err
    if r.status_code != 200:
        messages: list[str] = []
        code = _code(r, messages)
        soak.failed(kind, code, messages[0] if messages else "", t0)
        raise StepFailed(f"{kind}:{code}")
    job = r.json()
    if "state" in job and "kind" in job and job["state"] != "succeeded":
        error = job.get("error") or {}
        message = str(error.get("message", ""))
        if job["state"] == "running":  # the wait ran out: how and when did the job end?
            message = _followed(client, job, time.monotonic() - t0)
        code = str(error.get("code") or job["state"])
        soak.failed(kind, code, message, t0)
        raise StepFailed(f"{kind}:{code}")
    soak.note(soak.jobs, kind, t0)


def _followed(client: httpx.Client, job: dict[str, Any], waited_s: float) -> str:
    """A job still running when its ``wait`` answered, followed until it ends (at most
    ``FOLLOW_S``): its end state, error and last progress, for the report."""
    t0 = time.monotonic()
    now = job
    while now.get("state") == "running" and time.monotonic() - t0 < FOLLOW_S:
        time.sleep(0.5)
        with contextlib.suppress(httpx.HTTPError, ValueError):
            now = client.get(f"/api/v1/jobs/{job['id']}", headers=OPERATOR).json()
    error = now.get("error") or {}
    progress = {k: v for k, v in (now.get("progress") or {}).items() if k != "recent"}
    return (f"{job.get('kind')} {job.get('id')} still running after a {waited_s:.1f} s wait; "
            f"{now.get('state')} {time.monotonic() - t0:.1f} s later "
            f"({error.get('code')}: {error.get('message')}); progress {progress}")[:600]


def _cycle(soak: _Soak, client: httpx.Client, n: int) -> None:
    _step(soak, client, "home", "/api/v1/arm/home", {"wait": True})
    _step(soak, client, "locate", "/api/v1/locate", {})
    _step(soak, client, "approach_look_and_move", "/api/v1/approach",
          {"mode": "look_and_move", "wait": True})
    _step(soak, client, "gripper_close", "/api/v1/gripper", {"action": "close", "wait": True})
    _step(soak, client, "gripper_open", "/api/v1/gripper", {"action": "open", "wait": True})
    if n % SERVO_EVERY == SERVO_EVERY - 1:
        _step(soak, client, "home", "/api/v1/arm/home", {"wait": True})
        _step(soak, client, "approach_servo", "/api/v1/approach", {"mode": "servo", "wait": True})
        _step(soak, client, "track", "/api/v1/track",
              {"standoff_mm": 50.0, "duration_s": TRACK_S, "wait": True})


def _cycles(soak: _Soak, base: str, end_s: float, max_cycles: int | None,
            progress: Progress | None, total_s: float) -> None:
    start = time.monotonic()
    with httpx.Client(base_url=base, timeout=httpx.Timeout(120.0)) as client:
        n = 0
        while time.monotonic() < end_s and (max_cycles is None or n < max_cycles):
            code: str | None = None
            try:
                _cycle(soak, client, n)
            except StepFailed as err:
                code = err.code
                # whatever state the arm and gripper were left in: stop, activate the gripper
                # again (a stop or a fault leaves it not ready), so the next cycle starts clean
                with contextlib.suppress(httpx.HTTPError):
                    client.post("/api/v1/stop", json={"reason": "soak"}, headers=OPERATOR)
                    client.post("/api/v1/gripper", json={"action": "activate", "wait": True},
                                headers=OPERATOR)
                time.sleep(1.0)
            with soak.lock:
                soak.cycles.append((time.monotonic(), code))
            n += 1
            if progress is not None:
                progress("soak (s)", min(int(time.monotonic() - start), int(total_s)),
                         int(total_s))
    soak.stop.set()


def _poller(soak: _Soak, base: str, kind: str, path: str) -> None:
    with httpx.Client(base_url=base, headers=VIEWER, timeout=httpx.Timeout(10.0)) as client:
        while not soak.stop.is_set():
            t0 = time.monotonic()
            try:
                r = client.get(path)
                r.read()
                if r.status_code == 200:
                    soak.note(soak.latency, kind, t0)
                else:
                    with soak.lock:
                        soak.poll_errors[f"{kind}:{_code(r)}"] += 1
            except httpx.HTTPError as err:
                with soak.lock:
                    soak.poll_errors[f"{kind}:{type(err).__name__}"] += 1
                    soak.poll_timeouts.append((t0, f"{kind}:{type(err).__name__}"))
            soak.stop.wait(max(0.0, POLL_PERIOD_S - (time.monotonic() - t0)))


def _events(soak: _Soak, base: str) -> None:
    timeout = httpx.Timeout(10.0, read=30.0)
    while not soak.stop.is_set():
        try:
            with httpx.Client(base_url=base, headers=VIEWER, timeout=timeout) as client, \
                    client.stream("GET", "/api/v1/events") as r:
                for line in r.iter_lines():
                    if line.startswith("event:"):
                        with soak.lock:
                            soak.events += 1
                    if soak.stop.is_set():
                        return
        except httpx.HTTPError as err:
            with soak.lock:
                soak.poll_errors[f"events:{type(err).__name__}"] += 1
            soak.stop.wait(1.0)


def _rtde_reader(soak: _Soak, host: str) -> None:
    import rtde_receive

    try:
        r = rtde_receive.RTDEReceiveInterface(host, 125.0)
    except RuntimeError as err:
        soak.rtde_errors[f"connect:{err}"[:80]] += 1
        return
    period_s = 0.02
    try:
        last_ts, moved_s, woke_s, late_s = None, time.monotonic(), time.monotonic(), 0.0
        while not soak.stop.is_set():
            now = time.monotonic()
            late_s, woke_s = max(late_s, now - woke_s - period_s), now
            try:
                r.getActualTCPPose()
                r.getActualQ()
                ts = r.getTimestamp()
                with soak.lock:
                    soak.rtde_reads += 1
                    if ts != last_ts:
                        if last_ts is not None and now - moved_s > STREAM_GAP_S:
                            soak.stream_gaps.append((now, now - moved_s, late_s))
                        last_ts, moved_s, late_s = ts, now, 0.0
            except RuntimeError as err:
                with soak.lock:
                    soak.rtde_errors[str(err)[:80]] += 1
            soak.stop.wait(period_s)
    finally:
        with contextlib.suppress(RuntimeError):
            r.disconnect()


# -- the run -----------------------------------------------------------------------------------

def _sample(service: int, db: Path | None) -> dict[str, float | None]:
    # the ur_rtde child is looked up each time: the service starts a new one after a link loss
    pids = service_processes(service)
    svc, ur = pids["service"], pids.get("ur_client")
    return {
        "service_rss_mb": rss_mb(svc), "service_fds": fds(svc), "service_threads": threads(svc),
        "ur_client_rss_mb": None if ur is None else rss_mb(ur),
        "ur_client_fds": None if ur is None else fds(ur),
        "ur_client_threads": None if ur is None else threads(ur),
        "job_db_kb": None if db is None else round(_db_kb(db), 1),
    }


def run_soak(minutes: float, max_cycles: int | None = None, interfaces: bool = False,
             progress: Progress | None = None, burners: int = 0,
             service_nice: int | None = SERVICE_NICE, service_log: Path | None = None
             ) -> dict[str, Any]:
    """The soak; ``burners`` CPU-burning processes beside it for the whole run (a host as
    loaded as a busy cell PC), started before the service; ``service_log``: keep the
    service's warnings and errors there (to read beside the report's failures)."""
    loadavg_before = [round(x, 2) for x in os.getloadavg()]
    with contextlib.ExitStack() as stack:
        if burners > 0:
            from fakes.ur_controller.load import cpu_burners

            stack.enter_context(cpu_burners(burners, max_s=60.0 * minutes + 900.0))
        report = _run(minutes, max_cycles, interfaces, progress, loadavg_before, service_nice,
                      service_log)
    report["load"]["burners"] = burners
    return report


def _run(minutes: float, max_cycles: int | None, interfaces: bool,
         progress: Progress | None, loadavg_before: list[float],
         service_nice: int | None, service_log: Path | None) -> dict[str, Any]:
    soak = _Soak()
    samples: list[tuple[float, dict[str, float | None]]] = []
    extra = [] if interfaces else ["--opcua-port", "0", "--xmlrpc-port", "0",
                                   "--modbus-port", "0"]
    own_nice = os.getpriority(os.PRIO_PROCESS, 0)
    # The clients stand for a PLC, an operator's browser and a second RTDE client: other
    # machines, which the cell PC's load does not slow. Beside the burners at this process's
    # nice value they were starved instead (loopback TCP waited on their late ACKs and timed
    # out for 10-40 s while the service answered other clients at once), and measured
    # themselves. So they run at the service's nice value where the host allows it (the
    # threads started from here inherit it; the burners were started before).
    if service_nice is not None and service_nice < own_nice:
        with contextlib.suppress(PermissionError):
            os.setpriority(os.PRIO_PROCESS, 0, service_nice)
    client_nice = os.getpriority(os.PRIO_PROCESS, 0)
    try:
        report = _served(soak, samples, extra, minutes, max_cycles, interfaces, progress,
                         loadavg_before, service_nice, service_log)
    finally:
        with contextlib.suppress(PermissionError):
            os.setpriority(os.PRIO_PROCESS, 0, own_nice)
    report["load"]["client_nice"] = client_nice
    return report


def _served(soak: _Soak, samples: list[tuple[float, dict[str, float | None]]],
            extra: list[str], minutes: float, max_cycles: int | None, interfaces: bool,
            progress: Progress | None, loadavg_before: list[float],
            service_nice: int | None, service_log: Path | None) -> dict[str, Any]:
    with (serving(extra_args=extra, nice=service_nice, log_path=service_log) as (base, proc),
          KernelWaits(proc.pid) as soak.waits):
        nice_served = os.getpriority(os.PRIO_PROCESS, proc.pid)
        time.sleep(3.0)  # let the start settle (kernels, first frames, gripper activation)
        db = _job_db(proc.pid)
        host = urlparse(base).hostname or "127.0.0.1"
        start = time.monotonic()
        end_s = start + 60.0 * minutes
        workers = [threading.Thread(target=_poller, args=(soak, base, "status", "/api/v1/status"),
                                    daemon=True),
                   threading.Thread(target=_poller, args=(soak, base, "frame",
                                                          "/api/v1/camera/frame.jpg?overlay=true"),
                                    daemon=True),
                   threading.Thread(target=_events, args=(soak, base), daemon=True),
                   threading.Thread(target=_rtde_reader, args=(soak, host), daemon=True),
                   threading.Thread(target=_cycles, args=(soak, base, end_s, max_cycles,
                                                          progress, 60.0 * minutes),
                                    daemon=True)]
        for w in workers:
            w.start()
        samples.append((time.monotonic(), _sample(proc.pid, db)))
        while not soak.stop.wait(SAMPLE_S):
            samples.append((time.monotonic(), _sample(proc.pid, db)))
        samples.append((time.monotonic(), _sample(proc.pid, db)))
        for w in workers:  # the last cycle ends before the service does (a track: ~40 s)
            w.join(timeout=180.0)
        health = httpx.get(f"{base}/api/v1/health", timeout=5.0).json().get("status")
        stalls = _stalls(base)
    report = _report(soak, samples, start, minutes, max_cycles, interfaces, loadavg_before,
                     health)
    # the service held still for 0.1 s or more over the whole run: by the host (not
    # scheduled) or by a thread of its own (cell.supervision.host_watch)
    report["service_stalls"] = stalls
    report["load"]["service_nice"] = nice_served
    return report


def _stalls(base: str) -> dict[str, dict[str, float]]:
    """The service's own count of its stalls, from ``/metrics``."""
    from prometheus_client.parser import text_string_to_metric_families

    text = httpx.get(f"{base}/api/v1/metrics", headers=VIEWER, timeout=10.0).text
    out: dict[str, dict[str, float]] = {kind: {} for kind in KINDS}
    for family in text_string_to_metric_families(text):
        for sample in family.samples:
            by = sample.labels.get("by")
            if by in out and sample.name == "cell_stalls_total":
                out[by]["count"] = sample.value
            elif by in out and sample.name == "cell_stall_seconds_total":
                out[by]["seconds"] = round(sample.value, 2)
    return out


_STALL_NOTE = re.compile(r"for (\d+(?:\.\d+)?) s, (\d+(?:\.\d+)?) s before this failure")
KERNEL_WAIT_SHARE = 0.8  # of the blocked stall's length, spent with a thread in D
KERNEL_WAIT_MIN_SAMPLES = 3


def kernel_wait(since_s: float, now_s: float, message: str, waits: KernelWaits
                ) -> WaitRun | None:
    """For a failure after a *blocked* stall: the longest stretch between the step's start
    and the failure in which a thread of the service waited in the kernel (not placed by the
    note's "s before this failure", which the HTTP round trip would shift)."""
    if BLOCKED_STALL_MARK not in message:
        return None
    if _STALL_NOTE.search(message, message.index(BLOCKED_STALL_MARK)) is None:
        return None
    return waits.longest_run(since_s, now_s)


def in_kernel(message: str, run: WaitRun | None) -> bool:
    """Whether a failure's blocked stall was spent waiting in the kernel: a stretch of
    samples with a thread in D at least ``KERNEL_WAIT_SHARE`` of the stall's length."""
    if run is None or run.samples < KERNEL_WAIT_MIN_SAMPLES:
        return False
    note = _STALL_NOTE.search(message, message.index(BLOCKED_STALL_MARK))
    return note is not None and run.duration_s >= KERNEL_WAIT_SHARE * float(note[1])


def _report(soak: _Soak, samples: list[tuple[float, dict[str, float | None]]], start: float,
            minutes: float, max_cycles: int | None, interfaces: bool,
            loadavg_before: list[float], health: str | None) -> dict[str, Any]:
    t = [s[0] - start for s in samples]
    keys = list(samples[0][1])
    series = {k: [s[1][k] for s in samples] for k in keys}

    def minute_of(ts: float) -> int:
        return int((ts - start) // 60.0)

    per_minute = []
    for m in range(max(1, int(np.ceil(max(t[-1], 1e-9) / 60.0)))):
        last = [s for s in samples if minute_of(s[0]) <= m][-1][1]
        failed = [c for ts, c in soak.cycles if minute_of(ts) == m and c is not None]
        row: dict[str, Any] = {"minute": m + 1, **{k: _round(last[k]) for k in keys},
                               "cycles": sum(1 for ts, _ in soak.cycles if minute_of(ts) == m),
                               "failed_cycles": len(failed),
                               "failed_codes": dict(Counter(failed))}
        for kind in ("status", "frame"):
            ms = [v for ts, v in soak.latency[kind] if minute_of(ts) == m]
            row[f"{kind}_ms_p50"], row[f"{kind}_ms_p95"] = _pct(ms, 50), _pct(ms, 95)
        per_minute.append(row)
    failed = [c for _, c in soak.cycles if c is not None]
    first, final = samples[0][1], samples[-1][1]
    by_kernel = [in_kernel(m, run) for _, _, m, run in soak.failures]
    report: dict[str, Any] = {
        # the least kind figure first: the service's native growth, per hour
        "service_rss_mb_per_h": slope_per_h(t, series["service_rss_mb"], skip=0.1),
        "service_rss_mb_per_h_after_10_min": (
            slope_per_h(t, series["service_rss_mb"], skip=600.0 / t[-1])
            if t[-1] > 900.0 else None),
        "service_rss_mb_first": _round(first["service_rss_mb"]),
        "service_rss_mb_last": _round(final["service_rss_mb"]),
        "failed_cycles": len(failed),
        # failures whose message names the host (the service held still before them,
        # cell.supervision.host_watch), or after a blocked stall its threads spent waiting
        # in the kernel (cell.bench.kernel_waits); the rest are the cell's own
        "failed_cycles_not_host": sum(
            1 for (_, _, m, _), kernel in zip(soak.failures, by_kernel, strict=True)
            if HOST_STALL_MARK not in m and not kernel),
        # of those, failures after a stall of the service's own making (a thread that
        # held the interpreter): its defects, not the devices'
        "failed_cycles_own_stall": sum(1 for _, _, m, _ in soak.failures
                                       if OWN_STALL_MARK in m),
        # ... and after a thread blocked holding the interpreter (the kernel's or its own:
        # the service's stall-traces.txt says which)
        "failed_cycles_blocked_stall": sum(1 for _, _, m, _ in soak.failures
                                           if BLOCKED_STALL_MARK in m),
        # ... of which the service's threads waited in the kernel for most of the stall
        "failed_cycles_kernel_wait": sum(by_kernel),
        "failed_codes": dict(Counter(failed)),
        "cycles": len(soak.cycles),
        "ur_client_rss_mb_per_h": slope_per_h(t, series["ur_client_rss_mb"], skip=0.1),
        "fds_per_h": slope_per_h(t, series["service_fds"]),
        "threads_per_h": slope_per_h(t, series["service_threads"]),
        "ur_client_fds_per_h": slope_per_h(t, series["ur_client_fds"]),
        "ur_client_threads_per_h": slope_per_h(t, series["ur_client_threads"]),
        "job_db_kb_per_h": slope_per_h(t, series["job_db_kb"]),
        "fit_per_h": {k: slope_per_h(t, series[k]) for k in keys},
        "first": {k: _round(v) for k, v in first.items()},
        "last": {k: _round(v) for k, v in final.items()},
        "max": {k: _round(max((v for v in series[k] if v is not None), default=None))
                for k in keys},
        "status_ms_p50": _pct([v for _, v in soak.latency["status"]], 50),
        "status_ms_p95": _pct([v for _, v in soak.latency["status"]], 95),
        "frame_ms_p50": _pct([v for _, v in soak.latency["frame"]], 50),
        "frame_ms_p95": _pct([v for _, v in soak.latency["frame"]], 95),
        "status_polls": len(soak.latency["status"]),
        "frames": len(soak.latency["frame"]),
        "job_ms": {k: {"n": len(v), "p50": _pct([x for _, x in v], 50),
                       "p95": _pct([x for _, x in v], 95)} for k, v in soak.jobs.items()},
        "poll_errors": dict(soak.poll_errors),
        "sse_events": soak.events,
        "rtde_reads": soak.rtde_reads,
        "rtde_errors": dict(soak.rtde_errors),
        "error_messages": soak.error_messages,
        # each failed step: when (s into the run), which, and what the cell said
        "failures": [{"at_s": round(ts - start, 1), "code": code, "message": msg[:300],
                      **({} if msg.find(BLOCKED_STALL_MARK) < 0 else
                         {"stall": msg[msg.index(BLOCKED_STALL_MARK):][:200]}),
                      **({} if run is None else
                         {"kernel_wait_s": round(run.duration_s, 2),
                          "kernel_wait_samples": run.samples, "kernel_waits": run.wchans})}
                     for ts, code, msg, run in soak.failures],
        # the controller's RTDE timestamp seen standing still by the soak's own reader; a gap
        # with reader_late_s near zero was the controller's (or the link's), not the reader's
        "rtde_stream_max_gap_s": round(max((g for _, g, _ in soak.stream_gaps), default=0.0), 2),
        "rtde_stream_gaps": [{"at_s": round(ts - start, 1), "gap_s": round(g, 2),
                              "reader_late_s": round(late, 2)}
                             for ts, g, late in soak.stream_gaps[:50]],
        "poll_timeouts": [{"at_s": round(ts - start, 1), "what": what}
                          for ts, what in soak.poll_timeouts[:50]],
        "health_after": health,
        "per_minute": per_minute,
        "load": {"minutes": minutes, "max_cycles": max_cycles, "interfaces": interfaces,
                 "seconds": round(t[-1], 1), "sample_s": SAMPLE_S,
                 "poll_hz": round(1.0 / POLL_PERIOD_S, 1), "cores": os.cpu_count(),
                 "malloc_arena_max_env": os.environ.get("MALLOC_ARENA_MAX"),
                 "host_loadavg_before": loadavg_before,
                 "host_loadavg_after": [round(x, 2) for x in os.getloadavg()]},
    }
    return report


def _round(v: float | None) -> float | None:
    return None if v is None else round(float(v), 1)


def format_report(r: dict[str, Any]) -> str:
    lo = r["load"]
    lines = [
        f"service RSS {r['service_rss_mb_first']} -> {r['service_rss_mb_last']} MB, "
        f"{r['service_rss_mb_per_h']} MB/h after the first 10 % "
        f"({r['service_rss_mb_per_h_after_10_min']} MB/h after 10 min) "
        f"(ur_rtde child {r['ur_client_rss_mb_per_h']} MB/h); fds {r['fds_per_h']}/h, "
        f"threads {r['threads_per_h']}/h, job DB {r['job_db_kb_per_h']} KB/h",
        f"cycles {r['cycles']}, failed {r['failed_cycles']}: {r['failed_cycles_not_host']} "
        f"not the host's ({r['failed_cycles_own_stall']} after a stall of the service's own); "
        f"{r['failed_cycles_blocked_stall']} after a stall blocked holding the interpreter, "
        f"{r['failed_cycles_kernel_wait']} of them spent waiting in the kernel (the host's) "
        f"{r['failed_codes'] or ''}",
        "service stalls >= 0.1 s: " + ", ".join(
            f"{by} {v.get('count', '?')} ({v.get('seconds', '?')} s)"
            for by, v in r.get("service_stalls", {}).items()),
        f"status p50 {r['status_ms_p50']} ms p95 {r['status_ms_p95']} ms ({r['status_polls']}); "
        f"frame p50 {r['frame_ms_p50']} ms p95 {r['frame_ms_p95']} ms ({r['frames']}); "
        f"SSE events {r['sse_events']}; RTDE reads {r['rtde_reads']} "
        f"{r['rtde_errors'] or ''}; poll errors {r['poll_errors'] or 0}",
        "jobs (ms): " + ", ".join(f"{k} p50 {v['p50']} p95 {v['p95']} (n {v['n']})"
                                  for k, v in r["job_ms"].items()),
        f"{lo['seconds']} s on {lo['cores']} cores, host load average "
        f"{lo['host_loadavg_before']} before, {lo['host_loadavg_after']} after, "
        f"{lo.get('burners', 0)} CPU burners beside it",
        "min  svc MB  ur MB  fds thr  urthr  db KB  status p95  frame p95  cycles failed",
    ]
    for m in r["per_minute"]:
        lines.append(f"{m['minute']:3d} {m['service_rss_mb']!s:>7} {m['ur_client_rss_mb']!s:>6} "
                     f"{m['service_fds']!s:>4} {m['service_threads']!s:>3} "
                     f"{m['ur_client_threads']!s:>6} {m['job_db_kb']!s:>6} "
                     f"{m['status_ms_p95']!s:>11} {m['frame_ms_p95']!s:>10} "
                     f"{m['cycles']:>7} {m['failed_cycles']:>6} {m['failed_codes'] or ''}")
    return "\n".join(lines)
