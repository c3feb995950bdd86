"""``/metrics`` in the Prometheus text format, written plainly (a handful of series does not
need a client library): HTTP requests by route and status, locate outcomes and time, jobs by
final state, refusals by code, dead-man stops, and the live arm/camera gauges."""

from __future__ import annotations

import threading
import time
from collections import Counter, defaultdict
from typing import Any

from cell.service import Cell


class HttpStats:
    def __init__(self) -> None:
        self._lock = threading.Lock()
        self.requests: Counter[tuple[str, str, int]] = Counter()
        self.seconds: defaultdict[tuple[str, str], float] = defaultdict(float)

    def observe(self, method: str, route: str, status: int, seconds: float) -> None:
        with self._lock:
            self.requests[(method, route, status)] += 1
            self.seconds[(method, route)] += seconds

    def snapshot(self) -> tuple[dict[tuple[str, str, int], int], dict[tuple[str, str], float]]:
        with self._lock:
            return dict(self.requests), dict(self.seconds)


def _esc(v: Any) -> str:
    return str(v).replace("\\", "\\\\").replace('"', '\\"').replace("\n", "\\n")


def render(cell: Cell, http: HttpStats) -> str:
    lines: list[str] = []

    def metric(name: str, kind: str, help_text: str,
               samples: list[tuple[dict[str, Any], float]]) -> None:
        lines.append(f"# HELP {name} {help_text}")
        lines.append(f"# TYPE {name} {kind}")
        for labels, value in samples:
            lab = ",".join(f'{k}="{_esc(v)}"' for k, v in labels.items())
            lines.append(f"{name}{{{lab}}} {value}" if lab else f"{name} {value}")

    requests, seconds = http.snapshot()
    metric("cell_http_requests_total", "counter", "HTTP requests by route and status",
           [({"method": m, "route": r, "status": s}, n) for (m, r, s), n in requests.items()])
    metric("cell_http_request_seconds_total", "counter", "time spent answering, by route",
           [({"method": m, "route": r}, v) for (m, r), v in seconds.items()])
    st = cell.stats
    metric("cell_locate_total", "counter", "frames estimated by outcome",
           [({"outcome": k}, v) for k, v in cell.locator.outcomes.items()])
    metric("cell_locate_seconds_total", "counter", "time spent estimating successful frames",
           [({}, cell.locator.seconds_sum)])
    metric("cell_jobs_total", "counter", "finished jobs by final state",
           [({"state": k}, v) for k, v in st.jobs.items()])
    metric("cell_refusals_total", "counter", "refused commands by code",
           [({"code": k}, v) for k, v in st.refusals.items()])
    metric("cell_deadman_stops_total", "counter", "continuous jogs stopped by the dead-man",
           [({}, st.deadman_stops)])
    metric("cell_stops_total", "counter", "stop commands", [({}, st.stops)])
    status = cell.status()
    robot = status.get("robot", {})
    metric("cell_arm_connected", "gauge", "1 when the arm is connected",
           [({}, 1 if robot.get("connected") else 0)])
    metric("cell_arm_moving", "gauge", "1 while the arm moves", [({}, 1 if robot.get("moving")
                                                                 else 0)])
    metric("cell_arm_protective_stop", "gauge", "1 while protective-stopped",
           [({}, 1 if robot.get("protective_stop") else 0)])
    cam = status["camera"]
    metric("cell_camera_connected", "gauge", "1 while frames flow",
           [({}, 1 if cam["connected"] else 0)])
    if cam["last_frame_age_s"] is not None:
        metric("cell_camera_frame_age_seconds", "gauge", "age of the last frame served",
               [({}, cam["last_frame_age_s"])])
    metric("cell_uptime_seconds", "gauge", "since the service started",
           [({}, time.time() - cell.started_at)])
    return "\n".join(lines) + "\n"
