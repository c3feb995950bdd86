"""The soak bench's figures: growth as a least-squares slope per hour after the warm-up, and
what a failed step reports."""

from __future__ import annotations

import os
import time
from typing import Any

import httpx

from cell.bench.kernel_waits import KernelWaits, WaitShare, threads_in_d
from cell.bench.soak import StepFailed, _Soak, _step, kernel_wait, slope_per_h
from cell.supervision.host_watch import BLOCKED_STALL_MARK


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


def _waits_with(samples: list[tuple[float, list[str]]]) -> KernelWaits:
    waits = KernelWaits(pid=0)
    for t, in_d in samples:
        waits._times.append(t)
        if in_d:
            waits._waits[t] = in_d
    return waits


def test_a_blocked_stall_spent_waiting_in_the_kernel_is_the_hosts() -> None:
    # a 10 s blocked stall that ended 1 s before the failure at t = 111: samples every 0.1 s
    message = (f"the camera stalled ({BLOCKED_STALL_MARK} for 10.00 s, 1.0 s before this "
               "failure (the service used 0.40 s of CPU meanwhile): in the kernel ...)")
    stalled = [(100.0 + 0.1 * i, ["vma_prepare", "madvise_do_behavior"]) for i in range(100)]
    after = [(110.0 + 0.1 * i, []) for i in range(10)]
    w = kernel_wait(111.0, message, _waits_with(stalled + after))
    assert w is not None and w.share == 1.0 and 75 <= w.samples <= 85  # 1 s to 9 s in
    assert w.wchans == {"vma_prepare": w.samples, "madvise_do_behavior": w.samples}
    # the same stall with the threads running or asleep in Python: not the kernel's
    idle = _waits_with([(t, []) for t, _ in stalled + after])
    assert kernel_wait(111.0, message, idle) == WaitShare(0.0, w.samples, {})
    # other failures are not looked at
    assert kernel_wait(111.0, "the camera stalled", _waits_with(stalled)) is None


def test_the_kernel_wait_sampler_reads_a_live_process() -> None:
    assert threads_in_d(os.getpid()) == []  # this thread runs; none of ours is in D
    waits = KernelWaits(os.getpid(), period_s=0.01).start()
    time.sleep(0.2)
    waits.stop()
    share = waits.share(0.0, time.monotonic())
    assert share.samples >= 3 and share.share == 0.0
