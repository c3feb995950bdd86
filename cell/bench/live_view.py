"""``cell bench live-view``: CPU of the cell service (``cell serve``, simulated cell) with 0,
1 and 5 live viewers, for the shared JPEG live view and for the old per-request PNG frames.

    cell bench live-view [--seconds 15] [--json]

Each viewer does what the operator page does: fetch a frame with the overlay, show it, ask
again (JPEG: every 125 ms; the old PNG page: every 150 ms). The service's CPU is read from
/proc (user + system time of the server process and its threads) over the measuring window,
so the number is the service's own cost, whatever else the machine runs. The simulated camera
renders a frame only when one is asked for, so the numbers include that render (~a third of
a frame's cost here); a real camera delivers its frames for free.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import threading
import time
from pathlib import Path
from typing import Any

import httpx

from cell.bench.service import serving

HEADERS = {"Authorization": "Bearer sim-viewer"}


def _cpu_s(pid: int) -> float:
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def _viewer(url: str, path: str, period_s: float, stop: threading.Event,
            stats: dict[str, list[float]]) -> None:
    with httpx.Client(base_url=url, headers=HEADERS, timeout=10.0) as client:
        while not stop.is_set():
            t0 = time.monotonic()
            r = client.get(path)
            if r.status_code == 200:
                stats["bytes"].append(len(r.content))
                stats["latency_s"].append(time.monotonic() - t0)
            stop.wait(max(0.0, period_s - (time.monotonic() - t0)))


def measure(url: str, pid: int, path: str, period_s: float, viewers: int,
            seconds: float) -> dict[str, Any]:
    stop = threading.Event()
    stats: dict[str, list[float]] = {"bytes": [], "latency_s": []}
    threads = [threading.Thread(target=_viewer, args=(url, path, period_s, stop, stats),
                                daemon=True) for _ in range(viewers)]
    for t in threads:
        t.start()
    time.sleep(2.0)  # warm up
    n0 = len(stats["bytes"])
    c0, t0 = _cpu_s(pid), time.monotonic()
    time.sleep(seconds)
    c1, t1 = _cpu_s(pid), time.monotonic()
    n1 = len(stats["bytes"])
    stop.set()
    for t in threads:
        t.join(10)
    frames = n1 - n0
    return {
        "path": path, "viewers": viewers,
        "service_cpu_pct": round(100.0 * (c1 - c0) / (t1 - t0), 1),
        "frames_per_s_per_viewer": round(frames / (t1 - t0) / viewers, 2) if viewers else 0.0,
        "kb_per_frame": round(statistics.median(stats["bytes"]) / 1024, 1) if frames else 0.0,
        "median_latency_ms": round(1000 * statistics.median(stats["latency_s"]), 1)
        if frames else 0.0,
    }


def main(args: argparse.Namespace) -> int:
    runs = [("/api/v1/camera/frame.jpg?overlay=true", 0.125, n) for n in (0, 1, 5)]
    runs += [("/api/v1/camera/frame.png?overlay=true", 0.150, n) for n in (1, 5)]
    results = []
    with serving() as (url, proc):
        pid = proc.pid
        time.sleep(3.0)  # let start-up settle
        for path, period_s, viewers in runs:
            res = measure(url, pid, path, period_s, viewers, args.seconds)
            results.append(res)
            if not args.json:
                kind = "JPEG shared" if "jpg" in path else "PNG per request"
                print(f"{kind:16s} viewers {viewers}: service CPU {res['service_cpu_pct']:5.1f} % "
                      f"of a core, {res['frames_per_s_per_viewer']:4.1f} frames/s per viewer, "
                      f"{res['kb_per_frame']:6.1f} KB/frame, median {res['median_latency_ms']} ms",
                      flush=True)
    if args.json:
        print(json.dumps(results, indent=1))
    return 0

