"""``cell calibrate {check,reference}``: the calibration check on a running cell service.

A client of the HTTP API, as ``cell teach``: the service owns the arm and the camera, so
these ask it to run its jobs (``POST /api/v1/calibration/check`` and ``.../reference``, waited
for) rather than drive the hardware themselves. Exit status: 0 when the check says ``ok`` (or
the reference is recorded), 1 when it says ``drifted``, 2 on an error or a failed job.
"""

from __future__ import annotations

import argparse
import os
from typing import Any

from cell.commands.common import EXIT_NO, EXIT_OK, fail, print_json

JOB_TIMEOUT_S = 180.0  # the service waits up to 120 s for the job itself


def register(what: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    for name, text in (
            ("check", "check the calibration against the recorded reference on a running "
                      "service (exit 1 when it drifted)"),
            ("reference", "record the calibration reference around the arm's pose on a running "
                          "service (operator token)")):
        p = what.add_parser(name, help=text, description=text)
        p.add_argument("--url", default=os.environ.get("CELL_URL", "http://127.0.0.1:8000"),
                       help="the cell service (default $CELL_URL or http://127.0.0.1:8000)")
        p.add_argument("--token", default=os.environ.get("CELL_TOKEN"),
                       help="bearer token (default $CELL_TOKEN): operator or plc for check, "
                            "operator for reference")
        p.set_defaults(func=run, path=f"/api/v1/calibration/{name}")


def _client(args: argparse.Namespace) -> Any:
    """An httpx client for the service (tests substitute the in-process app's client)."""
    import httpx

    return httpx.Client(base_url=args.url, timeout=JOB_TIMEOUT_S)


def run(args: argparse.Namespace) -> int:
    import httpx

    if not args.token:
        return fail("unauthorized", "no token: pass --token or set CELL_TOKEN", args.json)
    try:
        r = _client(args).post(args.path, json={"wait": True},
                               headers={"Authorization": f"Bearer {args.token}"})
    except httpx.HTTPError as err:
        return fail("service_unreachable", f"cannot reach the cell at {args.url}: {err}",
                    args.json)
    try:
        job = r.json()
    except ValueError:
        return fail("bad_response", f"HTTP {r.status_code}: {r.text[:200]}", args.json)
    if r.status_code != 200:
        error = job.get("error", {}) if isinstance(job, dict) else {}
        return fail(error.get("code", f"http_{r.status_code}"),
                    error.get("message", r.text[:200]), args.json)
    if job.get("state") != "succeeded":
        error = job.get("error") or {}
        return fail(error.get("code") or job.get("state", "failed"),
                    error.get("message") or f"job {job.get('id')} {job.get('state')}",
                    args.json)
    result = job.get("result") or {}
    if args.json:
        print_json(job)
    else:
        print(_words(job["kind"], job["id"], result))
    return EXIT_NO if result.get("verdict") == "drifted" else EXIT_OK


def _words(kind: str, job_id: str, result: dict[str, Any]) -> str:
    if kind == "calibration_reference":
        return (f"reference recorded (job {job_id}): {len(result['views'])} views, spread "
                f"{result['spread_mm']:.3f} mm / {result['spread_deg']:.3f} deg")
    views = ", ".join(f"{v['distance_mm']:.3f}" for v in result["views"])
    return (f"calibration {result['verdict']} (job {job_id}, cause {result['cause']}): "
            f"{result['tcp_error_mm']:.3f} mm / {result['tcp_error_deg']:.3f} deg at the tool "
            f"(tolerance {result['tolerance_mm']:g} mm / {result['tolerance_deg']:g} deg); "
            f"views {views} mm; {result['took_s']:.1f} s")
