"""Waiting for a cell job through the HTTP API, as a PLC or the operator page would."""

from __future__ import annotations

from typing import Any

from tests.support.cell import AUTH
from tests.support.waiting import wait_until


def wait_job(client: Any, job_id: str, timeout_s: float = 60.0,
             headers: dict[str, str] | None = None, url: str = "/api/v1/jobs") -> dict[str, Any]:
    """The job once it has left ``running`` (any client with ``get``: TestClient, httpx)."""
    job: dict[str, Any] = {}

    def ended() -> bool:
        nonlocal job
        r = client.get(f"{url}/{job_id}", headers=headers or AUTH["viewer"])
        assert r.status_code == 200, r.text
        job = r.json()
        return job["state"] != "running"

    wait_until(ended, timeout_s, f"job {job_id} to end", poll_s=0.05)
    return job
