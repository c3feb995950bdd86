"""``cell bench soak``, shortened to one production cycle: the simulated cell served, the
cycle's jobs run, the pollers, the SSE stream and the RTDE reader answered, and every key of the
report there. Numbers are not judged here (a benchmark's job)."""

from __future__ import annotations

from cell.bench.soak import format_report, run_soak

PER_MINUTE_KEYS = {"minute", "service_rss_mb", "ur_client_rss_mb", "service_fds",
                   "service_threads", "ur_client_fds", "ur_client_threads", "job_db_kb",
                   "cycles", "failed_cycles", "failed_codes", "status_ms_p50", "status_ms_p95",
                   "frame_ms_p50", "frame_ms_p95"}


def test_the_soak_bench_runs_a_cycle_and_reports_every_key() -> None:
    r = run_soak(0.3, max_cycles=1)
    assert next(iter(r)) == "service_rss_mb_per_h"  # the least kind figure first
    for key in ("service_rss_mb_per_h", "ur_client_rss_mb_per_h", "fds_per_h", "threads_per_h",
                "job_db_kb_per_h", "status_ms_p50", "status_ms_p95", "frame_ms_p50",
                "frame_ms_p95", "service_rss_mb_first", "service_rss_mb_last"):
        assert key in r, key
    assert r["cycles"] == 1 and r["failed_cycles"] == 0, r["failed_codes"]
    for kind in ("home", "locate", "approach_look_and_move", "gripper_close", "gripper_open"):
        assert r["job_ms"][kind]["n"] >= 1 and r["job_ms"][kind]["p50"] > 0.0, kind
    assert set(r["job_ms"]) >= {"approach_servo", "track"}
    assert r["status_polls"] > 0 and r["frames"] > 0 and r["sse_events"] > 0
    assert r["rtde_reads"] > 0 and not r["rtde_errors"]
    assert r["per_minute"] and set(r["per_minute"][0]) == PER_MINUTE_KEYS
    assert r["first"]["service_rss_mb"] > 0 and r["first"]["service_threads"] > 0
    assert r["load"]["host_loadavg_before"] and r["health_after"] in ("ok", "degraded")
    assert "service RSS" in format_report(r)
