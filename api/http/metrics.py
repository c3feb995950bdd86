"""``/metrics`` through ``prometheus_client``: one registry per app (tests build many).

- ``cell_http_request_duration_seconds{method,route,status}``: latency histogram by route
  template (``/api/v1/jobs/{job_id}``, never the raw path, so ids do not explode the labels);
- ``cell_locate_request_seconds{outcome}``: POST /locate from request to answer;
  ``cell_locate_total{outcome}`` / ``cell_locate_seconds`` every estimate the cell made;
- ``cell_job_duration_seconds{kind,outcome}``: from start to end of every job;
- ``cell_stop_seconds``: POST /stop until the arm was told to stop;
- ``cell_stalls_total{by}`` / ``cell_stall_seconds_total{by}``: the service held still for
  0.1 s or more, by the host, a thread of its own computing or one blocked
  (cell.supervision.host_watch);
- ``cell_gripper_missed_reads_total``: background gripper status reads that failed;
- the cell's counters (jobs, refusals, dead-man stops, stops) and gauges (arm, camera);
- ``process_*`` (CPU, memory, file descriptors) and ``python_info``.
"""

from __future__ import annotations

import threading
from collections.abc import Iterator
from typing import Any

from prometheus_client import (
    CollectorRegistry,
    Histogram,
    PlatformCollector,
    ProcessCollector,
    generate_latest,
)
from prometheus_client.core import CounterMetricFamily, GaugeMetricFamily, Metric
from prometheus_client.registry import Collector

from cell.service import Cell
from cell.stats import CalibrationEvidence
from cell.supervision.host_watch import KINDS

LATENCY_BUCKETS_S = (0.001, 0.0025, 0.005, 0.01, 0.025, 0.05, 0.1, 0.25, 0.5, 1.0, 2.5, 5.0,
                     10.0, 30.0, 60.0)
JOBS_PER_SCRAPE = 200
JOB_BUCKETS_S = (0.5, 1.0, 2.0, 5.0, 10.0, 20.0, 30.0, 60.0, 120.0, 300.0, 600.0)


class _CellCollector(Collector):
    """The cell's own counters and gauges, read at scrape time."""

    def __init__(self, cell: Cell) -> None:
        self.cell = cell

    def collect(self) -> Iterator[Metric]:
        cell = self.cell
        st = cell.stats
        locates = CounterMetricFamily("cell_locate", "frames estimated by outcome",
                                      labels=["outcome"])
        for outcome, n in cell.locator.outcomes.items():
            locates.add_metric([outcome], n)
        yield locates
        yield CounterMetricFamily("cell_locate_seconds", "CPU-side time spent estimating "
                                  "successful frames", value=cell.locator.seconds_sum)
        jobs = CounterMetricFamily("cell_jobs", "finished jobs by end state", labels=["state"])
        for state, n in st.jobs.items():
            jobs.add_metric([state], n)
        yield jobs
        refusals = CounterMetricFamily("cell_refusals", "refused commands by code",
                                       labels=["code"])
        for code, n in st.refusals.items():
            refusals.add_metric([code], n)
        yield refusals
        yield CounterMetricFamily("cell_deadman_stops", "continuous jogs stopped by the "
                                  "dead-man", value=st.deadman_stops)
        yield CounterMetricFamily("cell_stops", "stop commands", value=st.stops)
        health = cell.health()
        yield GaugeMetricFamily("cell_arm_connected", "1 when the arm is connected",
                                value=1 if health["arm_connected"] else 0)
        yield GaugeMetricFamily("cell_camera_connected", "1 while frames flow",
                                value=1 if health["camera_connected"] else 0)
        try:
            arm = cell.arm_state()
            yield GaugeMetricFamily("cell_arm_moving", "1 while the arm moves",
                                    value=1 if arm.moving else 0)
            yield GaugeMetricFamily("cell_arm_protective_stop", "1 while protective-stopped",
                                    value=1 if arm.protective_stop else 0)
        except Exception:  # a disconnected arm: cell_arm_connected already says so
            pass
        yield GaugeMetricFamily("cell_started_time_seconds", "UNIX time the cell started",
                                value=cell.started_at)
        watch = cell.host_watch
        stalls = CounterMetricFamily(
            "cell_stalls", "times the service's threads stood still for 0.1 s or more, by "
            "who held them: host (the process was not scheduled), own (a thread of the "
            "service computed holding the interpreter), blocked (a thread blocked holding "
            "it: in the kernel or a call that does not release it)", labels=["by"])
        stall_s = CounterMetricFamily("cell_stall_seconds", "seconds the service's threads "
                                      "stood still in those stalls", labels=["by"])
        for by in KINDS:
            stalls.add_metric([by], watch.counts[by])
            stall_s.add_metric([by], watch.seconds[by])
        yield stalls
        yield stall_s
        yield CounterMetricFamily("cell_gripper_missed_reads", "background gripper status "
                                  "reads that failed (two in a row make a gripper fault)",
                                  value=cell.gripper_ops.missed_reads)
        yield from _calibration_metrics(st.calibration)


def _calibration_metrics(c: CalibrationEvidence) -> Iterator[Metric]:
    """What the jobs said about the calibration (cell.stats): a gauge appears once a job
    has said it."""
    yield CounterMetricFamily(
        "cell_calibration_inconsistent_jobs", "succeeded jobs whose views of a target at rest "
        "disagreed past the consistency limits", value=c.inconsistent)
    gauges = [
        ("cell_calibration_disagreement_mm", "the newest judged approach: how far the target "
         "at rest seemed to move while the arm moved (mm; 0 with a true calibration)",
         c.disagreement_mm),
        ("cell_calibration_disagreement_deg", "the same in degrees", c.disagreement_deg),
        ("cell_calibration_check_tcp_error_mm", "the newest calibration check's change at "
         "the tool (mm)", c.check_tcp_error_mm),
        ("cell_calibration_check_tcp_error_deg", "the same in degrees", c.check_tcp_error_deg),
        ("cell_calibration_check_drifted", "1 when the newest check said drifted",
         None if c.check_drifted is None else float(c.check_drifted)),
    ]
    for name, doc, value in gauges:
        if value is not None:
            yield GaugeMetricFamily(name, doc, value=value)


class Metrics:
    """The app's registry and the instruments routes and middleware observe."""

    def __init__(self, cell: Cell) -> None:
        self.registry = CollectorRegistry()
        ProcessCollector(registry=self.registry)
        PlatformCollector(registry=self.registry)
        self.registry.register(_CellCollector(cell))
        self.http = Histogram("cell_http_request_duration_seconds",
                              "HTTP request latency by route template and status",
                              ["method", "route", "status"], buckets=LATENCY_BUCKETS_S,
                              registry=self.registry)
        self.locate = Histogram("cell_locate_request_seconds", "POST /locate latency",
                                ["outcome"], buckets=LATENCY_BUCKETS_S, registry=self.registry)
        self.job = Histogram("cell_job_duration_seconds", "job duration by kind and outcome",
                             ["kind", "outcome"], buckets=JOB_BUCKETS_S,
                             registry=self.registry)
        self.stop = Histogram("cell_stop_seconds", "POST /stop until the arm was told to stop",
                              buckets=LATENCY_BUCKETS_S, registry=self.registry)
        self._cell = cell
        self._seen_jobs: dict[str, None] = dict.fromkeys(
            j.id for j in cell.jobs.list_jobs(JOBS_PER_SCRAPE) if j.finished)
        self._lock = threading.Lock()

    def observe_http(self, method: str, route: str, status: int, seconds: float) -> None:
        self.http.labels(method, route, str(status)).observe(seconds)

    def observe_job(self, job: dict[str, Any]) -> None:
        if job.get("state") in (None, "running") or job.get("ended_at") is None:
            return
        if job["id"] in self._seen_jobs:
            return
        self._seen_jobs[job["id"]] = None
        if len(self._seen_jobs) > 1000:  # bounded: forget the oldest
            self._seen_jobs.pop(next(iter(self._seen_jobs)))
        self.job.labels(job.get("kind", "job"), job["state"]).observe(
            max(0.0, float(job["ended_at"]) - float(job["created_at"])))

    def _collect_jobs(self) -> None:
        """Observe the jobs that ended since the last scrape (read from the job store at
        scrape time: no thread, no event subscription, and nothing lost while nobody
        scrapes, up to JOBS_PER_SCRAPE jobs between two scrapes)."""
        for job in reversed(self._cell.jobs.list_jobs(JOBS_PER_SCRAPE)):
            if job.finished:
                self.observe_job(job.as_dict())

    def close(self) -> None:
        """Nothing runs in the background; kept so the app can treat it like its peers."""

    def render(self) -> bytes:
        with self._lock:
            self._collect_jobs()
            return generate_latest(self.registry)
