"""The soak bench's figures: growth as a least-squares slope per hour after the warm-up, and
what a failed step reports."""

from __future__ import annotations

import os
import time
from typing import Any

import httpx
import pytest

from cell.bench.kernel_waits import KernelWaits, WaitRun, threads_in_d
from cell.bench.soak import StepFailed, _Soak, _step, in_kernel, kernel_wait, slope_per_h
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
        waits.add(t, in_d)
    return waits


# a 10 s blocked stall that ended 1 s before the failure at t = 111, as the host watch says it
BLOCKED = ("no frame examined for 10500 ms (limit 1000 ms: the camera or the estimator "
           "stalled); 0 frames without the target, 0 gated as jumps, 0 too old; the arm "
           f"stopped in 10 ms ({BLOCKED_STALL_MARK} "
           "for 10.00 s, 1.0 s before this failure (the service used 0.40 s of CPU meanwhile): "
           "in the kernel (a page read back from disk, kernel work the host starved) or in a "
           "call that does not release it; the stacks are in stall-traces.txt)")
STALLED = [(100.0 + 0.1 * i, ["vma_prepare", "madvise_do_behavior"]) for i in range(100)]
AFTER = [(110.0 + 0.1 * i, []) for i in range(10)]


def test_a_blocked_stall_spent_waiting_in_the_kernel_is_the_hosts() -> None:
    run = kernel_wait(95.0, 111.0, BLOCKED, _waits_with(STALLED + AFTER))
    assert run is not None and run.samples == 100 and run.duration_s == pytest.approx(10.0)
    assert run.wchans == {"vma_prepare": 100, "madvise_do_behavior": 100}
    assert in_kernel(BLOCKED, run)
    # the same stall with every thread running or asleep in Python: not the kernel's
    idle = kernel_wait(95.0, 111.0, BLOCKED, _waits_with([(t, []) for t, _ in STALLED + AFTER]))
    assert idle == WaitRun(0.0, 0, {}) and not in_kernel(BLOCKED, idle)
    # a second of it in the kernel is not the stall's cause
    brief = [(t, w if t < 101.0 else []) for t, w in STALLED]
    assert not in_kernel(BLOCKED, kernel_wait(95.0, 111.0, BLOCKED, _waits_with(brief)))
    # a sampler starved for 3 s in the middle does not make one stretch of the two halves
    starved = [(t, w) for t, w in STALLED if not 104.0 <= t < 107.0]
    split = kernel_wait(95.0, 111.0, BLOCKED, _waits_with(starved))
    assert split is not None and split.duration_s < 4.5 and not in_kernel(BLOCKED, split)
    # other failures are not looked at
    assert kernel_wait(95.0, 111.0, "the camera stalled", _waits_with(STALLED)) is None


def test_a_failed_steps_whole_message_is_judged() -> None:
    # the host watch's note comes last, past the first 200 characters of a long message
    assert BLOCKED.index("before this failure") > 200
    message = BLOCKED.replace("for 10.00 s, 1.0 s", "for 0.25 s, 0.0 s")
    soak = _Soak()
    soak.waits = waits = KernelWaits(pid=0)

    def answer(request: httpx.Request) -> httpx.Response:
        t = time.monotonic()  # the job's thread waits in the kernel while the step waits
        time.sleep(0.3)
        for i in range(28):
            waits.add(t + 0.01 * i, ["vma_prepare"])
        return httpx.Response(200, json={"id": "j2", "kind": "track", "state": "failed",
                                         "error": {"code": "target_lost", "message": message}})

    with (httpx.Client(base_url="http://cell", transport=httpx.MockTransport(answer)) as client,
          pytest.raises(StepFailed)):
        _step(soak, client, "track", "/api/v1/track", {"wait": True})
    ((_, code, kept, run),) = soak.failures
    assert code == "track:target_lost" and kept == message
    assert run is not None and run.samples == 28 and in_kernel(kept, run)


def test_the_kernel_wait_sampler_reads_a_live_process() -> None:
    assert threads_in_d(os.getpid()) == []  # this thread runs; none of ours is in D
    with KernelWaits(os.getpid(), period_s=0.01) as waits:
        time.sleep(0.2)
    run = waits.longest_run(0.0, time.monotonic())
    assert run == WaitRun(0.0, 0, {}) and len(waits._times) >= 3
