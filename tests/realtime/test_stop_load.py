"""STOP cuts through load, reads come from a fresh snapshot, a stalled SSE client blocks only
itself. Served by real uvicorn in a thread and driven over real sockets; the
timing bounds are generous (a loaded 2-core machine) and the outcomes are the arm's truth."""

from __future__ import annotations

import os
import socket
import threading
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import httpx
import numpy as np
import pytest

from api.app import create_app
from cell.service import Cell
from estimator.transforms import pose_distance
from fakes.ur_controller.process import free_loopback_host
from tests.support.browser import serve_app
from tests.support.cell import AUTH, running_cell, sim_config, tcp


class Pollers:
    """``n`` threads polling ``/status`` back to back until stopped; keeps latencies."""

    def __init__(self, base: str, n: int) -> None:
        self.base = base
        self.latencies_s: list[float] = []
        self.errors: list[str] = []
        self._stop = threading.Event()
        self._threads = [threading.Thread(target=self._run, daemon=True) for _ in range(n)]

    def _run(self) -> None:
        with httpx.Client(timeout=10.0) as c:
            while not self._stop.is_set():
                t0 = time.monotonic()
                try:
                    r = c.get(f"{self.base}/api/v1/status", headers=AUTH["viewer"])
                    if r.status_code != 200:
                        self.errors.append(str(r.status_code))
                except httpx.HTTPError as err:
                    self.errors.append(repr(err))
                self.latencies_s.append(time.monotonic() - t0)
                time.sleep(0.005)

    def __enter__(self) -> Pollers:
        for t in self._threads:
            t.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self._stop.set()
        for t in self._threads:
            t.join(timeout=15.0)


@pytest.fixture
def ur_served(tmp_path: Path) -> Iterator[tuple[Cell, str]]:
    config = sim_config(tmp_path, robot="ur", host=free_loopback_host())
    with running_cell(config) as cell, serve_app(create_app(cell)) as base:
        yield cell, base


@contextmanager
def _heartbeats(base: str) -> Iterator[None]:
    """Dead-man heartbeats every 50 ms while the block runs (refusals after a stop are fine)."""
    done = threading.Event()

    def beat() -> None:
        with httpx.Client(timeout=10.0) as c:
            while not done.wait(0.05):
                c.post(f"{base}/api/v1/jog/heartbeat", headers=AUTH["operator"])

    t = threading.Thread(target=beat, daemon=True)
    t.start()
    try:
        yield
    finally:
        done.set()
        t.join(timeout=10.0)


def _wait_moving(cell: Cell, start: np.ndarray, mm: float, timeout_s: float) -> None:
    deadline = time.monotonic() + timeout_s
    while pose_distance(tcp(cell), start)[0] < mm:
        assert time.monotonic() < deadline, "the arm never started moving"
        time.sleep(0.01)


def test_stop_under_load_reaches_the_arm(ur_served: tuple[Cell, str]) -> None:
    cell, base = ur_served
    with Pollers(base, 12) as pollers, httpx.Client(timeout=10.0) as c:
        for sign in (1.0, -1.0, 1.0):
            start = tcp(cell)
            # the dead-man must not end the jog before the stop: heartbeats run from before
            # the jog starts (begun after it, a loaded host let the 0.2 s dead-man expire first)
            with _heartbeats(base):
                r = c.post(f"{base}/api/v1/jog", headers=AUTH["operator"], json={
                    "mode": "continuous", "linear_mm_s": [0.0, 40.0 * sign, 0.0]})
                assert r.status_code == 200, r.text
                _wait_moving(cell, start, 0.5, timeout_s=5.0)
                t_sent = time.monotonic()
                r = c.post(f"{base}/api/v1/stop", headers=AUTH["operator"],
                           json={"reason": "test under load"})
            assert r.status_code == 200, r.text
            out = r.json()
            ended = [e.detail for e in cell.jobs.audit_log(20) if e.command == "jog_end"]
            assert out["stopped"] and out["cancelled"] == "jog", (out, "jog ends:", ended)
            # handed to the adapter promptly (bound: a loaded 2-core machine)
            assert out["commanded_monotonic_s"] - t_sent < 1.0, out
            assert out["sent_monotonic_s"] >= out["commanded_monotonic_s"]
            # the simulated arm really stops: still within a bounded time, and stays still
            deadline = time.monotonic() + 3.0
            prev = tcp(cell)
            while True:
                time.sleep(0.1)
                now = tcp(cell)
                if pose_distance(prev, now)[0] < 0.01:
                    break
                assert time.monotonic() < deadline, "the arm still moves 3 s after the stop"
                prev = now
            travelled = pose_distance(start, now)[0]
            # 40 mm/s: a stop that waited behind the pollers would have let it run on
            assert travelled < 40.0, f"the arm travelled {travelled:.1f} mm"
            time.sleep(0.3)
            assert pose_distance(now, tcp(cell))[0] < 0.01, "the arm moved again after the stop"
            deadline = time.monotonic() + 5.0
            while cell.status()["state"] == "jog":  # the jog loop has ended (slot free)
                assert time.monotonic() < deadline
                time.sleep(0.02)
    assert not pollers.errors, pollers.errors[:5]
    assert len(pollers.latencies_s) > 30
    stops = [c for c in cell.commanded() if c.kind == "stop"]
    assert stops, "no stop reached the guarded arm"
    audit = [e for e in cell.jobs.audit_log(200) if e.command == "stop"]
    assert len(audit) >= 3 and all(e.outcome == "ok" for e in audit[:3])


def _stalled_sse(base: str) -> socket.socket:
    """A client that asks for the event stream and never reads it."""
    host, port = base.removeprefix("http://").split(":")
    s = socket.socket()
    s.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4096)
    s.connect((host, int(port)))
    s.sendall(f"GET /api/v1/events HTTP/1.1\r\nHost: {host}\r\n"
              f"Authorization: Bearer sim-viewer\r\n\r\n".encode())
    return s


def test_a_client_that_never_reads_its_stream_does_not_stall_others(tmp_path: Path) -> None:
    with running_cell(sim_config(tmp_path)) as cell, serve_app(create_app(cell)) as base:
        stalled = [_stalled_sse(base) for _ in range(3)]
        try:
            deadline = time.monotonic() + 10.0
            while cell.events.n_subscribers < 3:
                assert time.monotonic() < deadline, "the stalled streams never subscribed"
                time.sleep(0.02)
            state_times: list[float] = []
            payload = "x" * 60_000
            stop_flood = threading.Event()

            def flood() -> None:  # enough bytes to fill every socket buffer of the stalled
                while not stop_flood.is_set():
                    cell.events.publish("flood", {"pad": payload})
                    time.sleep(0.004)

            def read(c: httpx.Client, until_s: float) -> None:
                with c.stream("GET", f"{base}/api/v1/events", headers=AUTH["viewer"]) as r:
                    for line in r.iter_lines():
                        if line == "event: state":
                            state_times.append(time.monotonic())
                        if time.monotonic() > until_s:
                            break

            flooder = threading.Thread(target=flood, daemon=True)
            with Pollers(base, 4) as pollers, httpx.Client(timeout=10.0) as c:
                flooder.start()
                read(c, time.monotonic() + 4.0)
                stop_flood.set()
                flooder.join(5.0)
            assert not pollers.errors, pollers.errors[:5]
            gaps = np.diff(state_times)
            period = 1.0 / cell.config.camera.fps
            print(f"reader: {len(state_times)} state events, max gap {gaps.max() * 1000:.0f} ms;"
                  f" status max {max(pollers.latencies_s) * 1000:.0f} ms while 3 streams stall")
            assert len(state_times) > 0.3 * 4.0 / period, len(state_times)
            # a stream held by the stalled ones waits out the whole 4 s window; a loaded 2-core
            # host running the suite beside it delays one event by up to 1.23 s (measured)
            assert gaps.max() < 2.0, f"the reader waited {gaps.max():.2f} s for a state event"
            assert max(pollers.latencies_s) < 2.0
            # the stalled clients are still subscribed, each with a bounded queue
            assert cell.events.n_subscribers >= 3
        finally:
            for s in stalled:
                s.close()


def test_the_snapshot_is_fresh_and_reads_do_not_call_the_arm(tmp_path: Path) -> None:
    with running_cell(sim_config(tmp_path)) as cell, serve_app(create_app(cell)) as base:
        period = cell.snapshot.period_s
        raw = cell.arm.raw
        calls = [0]
        original = raw.state

        def counting_state() -> Any:
            calls[0] += 1
            return original()

        raw.state = counting_state  # type: ignore[method-assign]
        try:
            ages: list[float] = []
            t0 = time.monotonic()
            with Pollers(base, 6) as pollers, httpx.Client(timeout=10.0) as c:
                while time.monotonic() - t0 < 2.0:
                    r = c.get(f"{base}/api/v1/status", headers=AUTH["viewer"])
                    assert r.status_code == 200
                    body = r.json()
                    ages.append(body["snapshot_age_s"])
                    assert body["robot"]["connected"] and "T_base_tcp" in body["robot"]
                    ages.append(cell.snapshot.current().age_s())
                    assert c.get(f"{base}/api/v1/health").json()["status"] == "ok"
            elapsed = time.monotonic() - t0
            n_reads = len(pollers.latencies_s) + len(ages)
        finally:
            raw.state = original  # type: ignore[method-assign]
        print(f"{n_reads} reads in {elapsed:.1f} s, {calls[0]} arm reads, snapshot age max "
              f"{max(ages) * 1000:.0f} ms (period {period * 1000:.0f} ms)")
        # never much older than a camera period: on a loaded 2-core host a refresh may wait
        # a scheduling quantum or two past its period
        assert max(ages) < 3 * period, max(ages)
        # the arm is read per refresh (camera rate, plus the link supervisor's checks), not
        # per request
        assert n_reads > 20
        refreshes = elapsed / period
        assert calls[0] < 3 * refreshes + elapsed / 0.1 + 10, (calls[0], n_reads)


def test_the_dead_man_stops_through_the_stop_path(tmp_path: Path) -> None:
    with running_cell(sim_config(tmp_path)) as cell:
        cell.jog_start("test", frame="base", linear_mm_s=[0.0, 0.0, 30.0],
                       angular_deg_s=[0.0, 0.0, 0.0])
        deadline = time.monotonic() + 5.0
        while cell.status()["state"] == "jog":  # no heartbeats: the dead-man ends it
            assert time.monotonic() < deadline, "the dead-man never stopped the jog"
            time.sleep(0.02)
        stops = [e for e in cell.jobs.audit_log(50) if e.command == "stop"]
        assert stops and "dead-man" in stops[0].params["reason"], stops
        assert stops[0].outcome == "ok"
        assert any(c.kind == "stop" for c in cell.commanded())
        still = tcp(cell)
        time.sleep(0.3)
        assert pose_distance(still, tcp(cell))[0] < 0.05


def test_the_service_bench_runs_its_load_and_reports_every_key() -> None:
    """``cell bench service``, shortened: the simulated cell served, idle CPU read, the load's
    clients (pollers in two processes, streams, a viewer) answered, STOP sent while jogging.
    Numbers are not judged here (a benchmark's job); only that every client got its answers."""
    from cell.bench.service import ServiceBenchConfig, run_service_bench

    r = run_service_bench(ServiceBenchConfig(duration_s=3.0, idle_s=1.0, pollers=6,
                                             streams=2, viewers=1, min_stops=5))
    assert r["errors"] == 0, r["error_samples"]
    assert r["stops"] >= 5 and r["stops_while_jogging"] >= 1
    assert r["status_polls"] >= 6 * 3 * 0.5  # 4 Hz each, over 3 s, on a slow host
    assert r["sse_state_events"] >= 2 * 10 and r["frames_viewed"] >= 3
    for key in ("stop_ms_p50", "stop_ms_p99", "status_ms_p99", "sse_gap_ms_max"):
        assert isinstance(r[key], float) and r[key] >= 0.0, (key, r[key])
    assert set(r["idle_cpu_pct"]) == {"service", "ur_client", "controller"}
    # served as the systemd unit runs it where the host allows raising priority (root here)
    if os.geteuid() == 0:
        assert r["nice"]["service"] == -5 and r["nice"]["ur_client"] == -5, r["nice"]
    assert r["health_after"] in ("ok", "degraded")
