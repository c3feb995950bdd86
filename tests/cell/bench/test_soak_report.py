"""The soak bench's figures: growth as a least-squares slope per hour after the warm-up, and
what a failed step reports."""

from __future__ import annotations

from typing import Any

import httpx

from cell.bench.soak import StepFailed, _Soak, _step, slope_per_h


def test_the_slope_is_per_hour_and_skips_the_warm_up() -> None:
    t = [60.0 * i for i in range(11)]  # ten minutes
    rss = [400.0 + (50.0 if i == 0 else 0.0) + 1.0 * i for i in range(11)]  # +1 MB/min
    assert slope_per_h(t, rss, skip=0.1) == 60.0  # the first sample's spike is left out
    assert slope_per_h(t, [5.0] * 11) == 0.0
    assert slope_per_h(t[:2], rss[:2]) is None  # too few samples to fit a line
    assert slope_per_h([], []) is None


def test_a_job_still_running_after_its_wait_is_followed_to_its_end() -> None:
    polls: list[str] = []

    def answer(request: httpx.Request) -> httpx.Response:
        job: dict[str, Any] = {"id": "j1", "kind": "track", "state": "running",
                               "progress": {"phase": "track"}, "error": None}
        if request.method == "GET":
            polls.append(request.url.path)
            if len(polls) >= 2:
                job |= {"state": "failed", "progress": {"phase": "target_lost", "recent": [1]},
                        "error": {"code": "target_lost", "message": "covered"}}
        return httpx.Response(200, json=job)

    soak = _Soak()
    with httpx.Client(base_url="http://cell", transport=httpx.MockTransport(answer)) as client:
        try:
            _step(soak, client, "track", "/api/v1/track", {"wait": True})
        except StepFailed as failed:
            assert failed.code == "track:running"
        else:
            raise AssertionError("a job still running is a failed step")
    assert polls == ["/api/v1/jobs/j1"] * 2
    (message,) = soak.error_messages
    assert "still running after" in message and "failed" in message
    assert "target_lost: covered" in message and "'phase': 'target_lost'" in message
    assert "recent" not in message
