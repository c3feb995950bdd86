"""A job database of many days, built from real rows: what a cell's service costs as it ages.

``python -m cell.bench.aged_db build SOURCE.db OUT.db --days 30 [--jobs-per-h 404
--audit-per-h 1427]`` copies the jobs, audit rows and alarms a service wrote in a short run
(SOURCE, e.g. a soak's database) over and over, with new ids and times spread evenly over
the last ``days`` days, at the given rates (the defaults are the 15-minute soak's). Each
failed job gets its alarm, acknowledged, as the service would have raised it; the alarm log's
start is the first day.
The file keeps SOURCE's schema (tables and indexes as the version that wrote it made them),
so the same file serves to measure the version before a change and the one after it.

``python -m cell.bench.aged_db measure DB [--tree DIR] [--idle-s 60]`` serves the simulated
cell (``cell serve``, the code in ``DIR`` first on the path) on a copy of DB and reports the
start-up (process start until ``/api/v1/health`` says the start has ended, and until it first
answered; then the first ``/api/v1/alarms``)
and the service's CPU while idle (its user and system time over ``idle-s`` from ``/proc``).
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import shutil
import signal
import sqlite3
import subprocess
import sys
import tempfile
import time
import uuid
from pathlib import Path
from typing import Any

import httpx

from cell.supervision.status import still_starting

BATCH = 5000


def build(source: Path, out: Path, days: float, jobs_per_h: float, audit_per_h: float,
          now_s: float | None = None) -> dict[str, Any]:
    now = time.time() if now_s is None else now_s
    start = now - days * 86400.0
    src = sqlite3.connect(source)
    jobs = src.execute("SELECT kind, caller, params, state, progress, result, error_code, "
                       "error_message, created_at, ended_at, pid FROM jobs "
                       "WHERE state != 'running' ORDER BY created_at").fetchall()
    audit = src.execute("SELECT caller, command, params, outcome, detail, started_at, "
                        "ended_at FROM audit ORDER BY id").fetchall()
    schema = [r[0] for r in src.execute(
        "SELECT sql FROM sqlite_master WHERE sql IS NOT NULL AND name NOT LIKE 'sqlite_%'")]
    src.close()
    if not jobs or not audit:
        raise SystemExit(f"{source} holds no ended jobs or no audit rows to copy")
    out.unlink(missing_ok=True)
    db = sqlite3.connect(out, isolation_level=None)
    db.execute("PRAGMA journal_mode=WAL")
    for sql in schema:
        db.execute(sql)
    n_jobs, n_audit = int(days * 24 * jobs_per_h), int(days * 24 * audit_per_h)
    db.execute("BEGIN")
    alarms = 0
    for i in range(n_jobs):
        row = jobs[i % len(jobs)]
        t = start + (i + 0.5) * (now - start) / n_jobs
        duration = max(0.0, float(row[9] or row[8]) - float(row[8]))
        job_id = uuid.uuid4().hex[:12]
        db.execute("INSERT INTO jobs (id, kind, caller, params, state, progress, result, "
                   "error_code, error_message, created_at, ended_at, pid) VALUES "
                   "(?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?)",
                   (job_id, *row[:8], t, t + duration, row[10]))
        if row[3] in ("failed", "interrupted") or (row[3] == "cancelled"
                                                   and row[6] != "cancelled"):
            db.execute("INSERT INTO alarms (key, source, code, message, job_id, raised_at, "
                       "acked_at, acked_by) VALUES (?, 'job', ?, ?, ?, ?, ?, 'operator')",
                       (f"job:{job_id}", row[6] or row[3], row[7] or row[3], job_id,
                        t + duration, t + duration + 60.0))
            alarms += 1
        if i % BATCH == BATCH - 1:
            db.execute("COMMIT")
            db.execute("BEGIN")
    for i in range(n_audit):
        row = audit[i % len(audit)]
        t = start + (i + 0.5) * (now - start) / n_audit
        db.execute("INSERT INTO audit (caller, command, params, outcome, detail, started_at, "
                   "ended_at) VALUES (?, ?, ?, ?, ?, ?, ?)",
                   (*row[:5], t - max(0.0, float(row[6]) - float(row[5])), t))
        if i % BATCH == BATCH - 1:
            db.execute("COMMIT")
            db.execute("BEGIN")
    db.execute("INSERT OR REPLACE INTO alarm_meta (key, value) VALUES ('jobs_since', ?)",
               (start,))
    db.execute("COMMIT")
    db.execute("PRAGMA wal_checkpoint(TRUNCATE)")
    db.close()
    return {"jobs": n_jobs, "audit_rows": n_audit, "alarms": alarms,
            "source_jobs": len(jobs), "source_audit_rows": len(audit),
            "size_mb": round(out.stat().st_size / 1024 / 1024, 1)}


def _cpu_s(pid: int) -> float:
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def measure(db: Path | None, tree: Path | None, idle_s: float) -> dict[str, Any]:
    """Start-up and idle CPU of ``cell serve`` on a copy of ``db`` (None: a fresh one)."""
    from cell.bench.service import _config_text, _free_port
    from fakes.ur_controller.process import free_loopback_host

    host = free_loopback_host()
    port = _free_port(host)
    with tempfile.TemporaryDirectory(prefix="cell-aged-") as tmp:
        state = Path(tmp)
        if db is not None:
            shutil.copy(db, state / "jobs.db")
        cfg = state / "cell.toml"
        cfg.write_text(_config_text(host, state))
        env = dict(os.environ)
        if tree is not None:
            env["PYTHONPATH"] = str(tree)
        t0 = time.monotonic()
        proc = subprocess.Popen(
            [sys.executable, "-m", "cell", "serve", "--config", str(cfg), "--host", host,
             "--port", str(port), "--log-level", "warning"], env=env,
            stdout=subprocess.DEVNULL, stderr=open(state / "serve.log", "wb"))  # noqa: SIM115
        base = f"http://{host}:{port}/api/v1"
        headers = {"Authorization": "Bearer sim-viewer"}
        try:
            answered_s: float | None = None
            while True:
                if proc.poll() is not None:
                    raise RuntimeError((state / "serve.log").read_text()[-2000:])
                with contextlib.suppress(httpx.HTTPError):
                    r = httpx.get(f"{base}/health", timeout=2.0)
                    if r.status_code == 200:
                        answered_s = answered_s or time.monotonic() - t0
                        if not still_starting(r.json()):
                            break
                time.sleep(0.05)
            startup_s = time.monotonic() - t0
            t1 = time.monotonic()
            httpx.get(f"{base}/alarms", headers=headers, timeout=30.0).raise_for_status()
            alarms_s = time.monotonic() - t1
            time.sleep(5.0)  # the start's own work settles
            c0, w0 = _cpu_s(proc.pid), time.monotonic()
            time.sleep(idle_s)
            cpu = (_cpu_s(proc.pid) - c0) / (time.monotonic() - w0)
            size_mb = (state / "jobs.db").stat().st_size / 1024 / 1024
        finally:
            proc.send_signal(signal.SIGTERM)
            try:
                proc.wait(30)
            except subprocess.TimeoutExpired:
                proc.kill()
    return {"db": str(db) if db else "fresh", "tree": str(tree or "installed"),
            # the least kind first: until the start has ended (the arm connected and
            # powered on), then until the API first answered (/health "starting")
            "startup_s": round(startup_s, 2), "first_answer_s": round(answered_s or 0.0, 2),
            "first_alarms_s": round(alarms_s, 3),
            "idle_cpu_pct": round(100 * cpu, 1), "idle_s": idle_s,
            "db_size_mb": round(size_mb, 1), "loadavg": os.getloadavg()}


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0] if __doc__ else None)
    sub = p.add_subparsers(dest="what", required=True)
    b = sub.add_parser("build")
    b.add_argument("source", type=Path)
    b.add_argument("out", type=Path)
    b.add_argument("--days", type=float, default=30.0)
    b.add_argument("--jobs-per-h", type=float, default=404.0)
    b.add_argument("--audit-per-h", type=float, default=1427.0)
    m = sub.add_parser("measure")
    m.add_argument("db", nargs="?", type=Path, help="none: a fresh database")
    m.add_argument("--tree", type=Path, help="the source tree to serve (PYTHONPATH)")
    m.add_argument("--idle-s", type=float, default=60.0)
    a = p.parse_args(argv)
    if a.what == "build":
        print(json.dumps(build(a.source, a.out, a.days, a.jobs_per_h, a.audit_per_h)))
    else:
        print(json.dumps(measure(a.db, a.tree, a.idle_s)))


if __name__ == "__main__":
    main()
