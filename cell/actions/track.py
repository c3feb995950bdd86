"""Track: hold the TCP at a standoff pose relative to a moving target (a conveyor).

A job like an approach, in servo mode without convergence: it runs until ``stop``,
``duration_s`` (capped by ``[servo] max_track_s``) or the loss of the target
(``target_lost``). The loop is :mod:`cell.actions.loop` with its position-based law; the goal
and the duration are checked before the job starts, so a refusal moves nothing. A recipe's dot
layout (``layout``) is looked for during the job only (:class:`cell.actions.approach.JobLayout`).
"""

from __future__ import annotations

from typing import Any

import numpy as np
from numpy.typing import NDArray

from cell.actions.approach import JobLayout, locate
from cell.actions.approach_rules import check_standoff
from cell.actions.loop.position import PositionLaw, ServoGoal
from cell.actions.loop.runner import ClosedLoop
from cell.core import CellCore
from cell.error_codes import ErrorCode
from cell.errors import LimitError, UnavailableError
from cell.jobs.store import Job
from cell.motion.guard import Motion
from cell.vision.frames import approach_tcp
from cell.vision.locate import Located
from estimator import Target
from estimator.transforms import pose_dict

Matrix4 = NDArray[np.float64]


def start_track(core: CellCore, caller: str, *, standoff_mm: float, duration_s: float,
                T_target_tcp: Matrix4 | None = None, wait: bool = False,
                wait_timeout_s: float = 120.0, recipe: dict[str, Any] | None = None,
                layout: Target | None = None) -> Job:
    sc = core.config.servo
    T_tt = (core.config.approach.T_target_tcp.T() if T_target_tcp is None
            else np.asarray(T_target_tcp, dtype=float))
    standoff, duration = float(standoff_mm), float(duration_s)
    params: dict[str, Any] = {"standoff_mm": standoff, "duration_s": duration,
                              "T_target_tcp": pose_dict(T_tt)}
    if recipe is not None:
        params["recipe"] = recipe  # the record of the recipe the job tracks with
    first: list[Located] = []
    lent = JobLayout(core, layout)

    def checks(motion: Motion) -> None:
        check_standoff(standoff)
        if not (np.isfinite(duration) and 0 < duration <= sc.max_track_s):
            raise LimitError(ErrorCode.duration_limit, f"duration_s must be within (0, "
                             f"{sc.max_track_s}] (servo.max_track_s), got {duration_s}")
        st = core.arm.ready_state()
        if not core.camera.is_connected:
            raise UnavailableError(ErrorCode.camera_lost, "the camera is lost: tracking needs it")
        loc = locate(core, 1)
        core.arm.guard.check_goal(st.T_base_tcp, approach_tcp(loc.T_base_target, T_tt, standoff),
                                  "tracking goal")
        first.append(loc)

    def work(job_id: str, motion: Motion) -> dict[str, Any]:
        try:
            return ClosedLoop(core, job_id, motion, PositionLaw(core, ServoGoal(T_tt, standoff),
                                                                "track"),
                              duration_s=duration).run(first[0])
        finally:
            lent.ended()

    return lent.start_job("track", caller, params, work, checks, wait=wait,
                          wait_timeout_s=wait_timeout_s)
