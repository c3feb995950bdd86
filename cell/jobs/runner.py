"""One job lifecycle for every long-running command (approach, calibration, home).

claim the motion slot -> check -> create the job -> run in a thread -> finish by how it ended
-> count -> audit -> publish. Written once here, so every kind of job ends the same way:
``succeeded`` with its result, ``cancelled`` by a stop, ``failed`` with a typed code and a
message in words (the arm commanded to stop and still first), never left ``running``.
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable
from typing import Any

from cell.error_codes import ErrorCode
from cell.errors import Cancelled, CellError
from cell.jobs.audit import Auditor
from cell.jobs.events import EventBus
from cell.jobs.store import Job, JobStore
from cell.motion.guard import GuardedArm, Motion, MotionSlot, driver_error
from cell.results.jobs import JobResult, result_of
from cell.stats import CellStats
from drivers.errors import DriverError

log = logging.getLogger(__name__)

# (job id, motion) -> the result model of the job's kind
Work = Callable[[str, Motion], JobResult]
Check = Callable[[Motion], None]  # raises CellError to refuse; runs holding the slot
OnEnd = Callable[[Job], None]  # told of the started and the ended job, after the "job" event


class JobRunner:
    def __init__(self, jobs: JobStore, slot: MotionSlot, arm: GuardedArm, events: EventBus,
                 audit: Auditor, stats: CellStats,
                 host_note: Callable[[float], str | None] | None = None) -> None:
        """``host_note(since_s)``: a sentence when the host held the service still since
        then (cell.supervision.host_watch), added to a failed job's message."""
        self.jobs = jobs
        self.host_note = host_note
        self.slot = slot
        self.arm = arm
        self.events = events
        self.audit = audit
        self.stats = stats
        self._threads: list[threading.Thread] = []
        self._lock = threading.Lock()

    def start(self, kind: str, caller: str, params: dict[str, Any], work: Work, *,
              check: Check | None = None, needs_camera: bool = False, wait: bool = False,
              wait_timeout_s: float = 120.0, on_change: OnEnd | None = None,
              motion_name: str | None = None) -> Job:
        """Start ``work`` as a job holding the motion slot; refusals (from ``check``, or
        ``busy``) raise CellError before any job exists, and are audited. With ``wait``,
        return the job once it has ended (or after ``wait_timeout_s``, still running)."""
        with self.audit.command(caller, kind, params) as note:
            motion = self.slot.claim(motion_name or kind, needs_camera=needs_camera)
            try:
                if check is not None:
                    check(motion)
                job = self.jobs.create(kind, caller, params)
            except BaseException:
                self.slot.release(motion)
                raise
            motion.job_id = note.job_id = job.id
            note.detail = "started"
            thread = threading.Thread(target=self._run, args=(job, motion, work, on_change),
                                      name=f"{kind}-{job.id}", daemon=True)
            with self._lock:
                self._threads = [t for t in self._threads if t.is_alive()] + [thread]
            thread.start()
        self.publish(job)
        if on_change is not None:
            on_change(job)
        if wait:
            thread.join(timeout=wait_timeout_s)
            ended = self.jobs.get(job.id)
            assert ended is not None
            return ended
        return job

    def _with_host(self, message: str, started_s: float) -> str:
        """``message``, and what the host did to the service meanwhile when it matters."""
        note = None if self.host_note is None else self.host_note(started_s)
        return message if note is None else f"{message} ({note})"

    def progress(self, job_id: str, info: dict[str, Any]) -> None:
        self.jobs.set_progress(job_id, info)

    def publish(self, job: Job) -> None:
        self.events.publish("job", {"job": job.as_dict()})

    def join(self, timeout_s: float) -> None:
        with self._lock:
            threads = list(self._threads)
        for t in threads:
            t.join(timeout=timeout_s)

    def _run(self, job: Job, motion: Motion, work: Work, on_change: OnEnd | None) -> None:
        started_s = time.monotonic()
        try:
            # a result that is not a model of the job's kind fails the job (internal_error)
            # rather than publish a shape the job's schema does not show
            result = result_of(job.kind, work(job.id, motion))
            if motion.cancel.is_set() and motion.reason is not None:
                raise motion.reason
            if not self.slot.release_unless_cancelled(motion):
                # a stop reached the job after its last motion: it answered that it cancelled
                # this job, so the job says so too
                raise Cancelled(ErrorCode.cancelled, "stopped by request as the job ended")
            ended = self.jobs.finish(job.id, "succeeded", result)
        except Cancelled as err:
            self.arm.settle()
            ended = self.jobs.finish(job.id, "cancelled", None, err.code, err.message)
        except CellError as err:
            self.arm.settle()
            ended = self.jobs.finish(job.id, "failed", None, err.code,
                                     self._with_host(err.message, started_s))
        except DriverError as err:
            self.arm.settle()
            e = driver_error(err, f"{job.kind}")
            ended = self.jobs.finish(job.id, "failed", None, e.code,
                                     self._with_host(e.message, started_s))
        except Exception as err:
            log.exception("%s job %s crashed", job.kind, job.id)
            self.arm.settle()
            ended = self.jobs.finish(job.id, "failed", None, "internal_error", repr(err))
        finally:
            self.slot.release(motion)
        self.stats.count_job_end(ended.state)
        self.stats.observe_result(ended.result)
        self.audit.record(ended.caller, f"{ended.kind}_end", {"job_id": ended.id}, ended.state,
                          ended.error_message or "", ended.id, ended.created_at)
        self.publish(ended)
        if on_change is not None:
            on_change(ended)
