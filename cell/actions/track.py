"""Track: hold the TCP at a standoff pose relative to a moving target (a conveyor), or hold the
taught view of a target while it moves (mode ``"ibvs"``).

A job like an approach without convergence: the closed loop (:mod:`cell.servoing`) with its
position-based law, or its image-based one, runs until ``stop``, ``duration_s`` (capped by
``[servo] max_track_s``) or the loss of the target (``target_lost``). The goal and the duration
are checked before the job starts, so a refusal moves nothing. A recipe's dot layout
(``layout``) is looked for during the job only (:class:`cell.actions.approach.JobLayout`).

The image-based law has no feed-forward of the target's motion, so a moving target is followed
with a lag of ``speed / gain``: it is for slow drifts and for holding a view, the pose-based
track for conveyors.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import numpy as np
from numpy.typing import NDArray

from cell.actions.approach import JobLayout, check_ibvs_request, locate
from cell.actions.approach_rules import check_standoff
from cell.core import CellCore
from cell.error_codes import ErrorCode
from cell.errors import LimitError, RefusedError, UnavailableError
from cell.jobs.store import Job
from cell.motion.guard import Motion
from cell.results import IbvsTrack, ServoTrack
from cell.servoing.ibvs import Features
from cell.servoing.image import ImageLaw
from cell.servoing.position import PositionLaw, ServoGoal
from cell.servoing.runner import ClosedLoop
from cell.vision.frames import approach_tcp
from cell.vision.locate import Located
from estimator import Target
from estimator.transforms import pose_dict

Matrix4 = NDArray[np.float64]


def start_track(core: CellCore, caller: str, *, standoff_mm: float, duration_s: float,
                T_target_tcp: Matrix4 | None = None, wait: bool = False,
                wait_timeout_s: float = 120.0, recipe: dict[str, Any] | None = None,
                layout: Target | None = None) -> Job:
    T_tt = _T_target_tcp(core, T_target_tcp)
    standoff = float(standoff_mm)
    params: dict[str, Any] = {"standoff_mm": standoff, "duration_s": float(duration_s),
                              "T_target_tcp": pose_dict(T_tt)}
    if recipe is not None:
        params["recipe"] = recipe  # the record of the recipe the job tracks with
    first: list[Located] = []
    lent = JobLayout(core, layout)

    def checks(motion: Motion) -> None:
        check_standoff(standoff)
        first.append(_checked_start(core, duration_s, lambda T_bt: approach_tcp(
            T_bt, T_tt, standoff)))

    def work(job_id: str, motion: Motion) -> ServoTrack:
        try:
            return ServoTrack(mode="track", **ClosedLoop(
                core, job_id, motion, PositionLaw(core, ServoGoal(T_tt, standoff), "track"),
                duration_s=float(duration_s)).run(first[0]))
        finally:
            lent.ended()

    return lent.start_job("track", caller, params, work, checks, wait=wait,
                          wait_timeout_s=wait_timeout_s)


def start_ibvs_track(core: CellCore, caller: str, *, standoff_mm: float, duration_s: float,
                     T_target_tcp: Matrix4 | None, view: Features | None, wait: bool = False,
                     wait_timeout_s: float = 120.0) -> Job:
    check_ibvs_request(view, standoff_mm)
    if core.frames.is_fixed:
        raise RefusedError(ErrorCode.not_supported, "tracking by IBVS is for a camera on the "
                           "flange (a fixed camera's IBVS drives the tool's plate to a taught "
                           "view: approach)")
    T_tt = _T_target_tcp(core, T_target_tcp)
    params = {"standoff_mm": 0.0, "duration_s": float(duration_s),
              "T_target_tcp": pose_dict(T_tt), "mode": "ibvs"}

    def check(motion: Motion) -> None:
        _checked_start(core, duration_s, lambda T_bt: T_bt @ T_tt)

    def work(job_id: str, motion: Motion) -> IbvsTrack:
        assert view is not None
        return IbvsTrack(mode="ibvs_track", **ClosedLoop(
            core, job_id, motion, ImageLaw(core, view, T_tt, "track"),
            duration_s=float(duration_s)).run())

    return core.runner.start("track", caller, params, work, check=check, needs_camera=True,
                             wait=wait, wait_timeout_s=wait_timeout_s)


def _T_target_tcp(core: CellCore, T_target_tcp: Matrix4 | None) -> Matrix4:
    return (core.config.approach.T_target_tcp.T() if T_target_tcp is None
            else np.asarray(T_target_tcp, dtype=float))


def _checked_start(core: CellCore, duration_s: float, goal: Callable[[Matrix4], Matrix4]
                   ) -> Located:
    """A track's checks: its duration, the arm ready, the camera there, the target located and
    the ``goal`` it gives (of ``T_base_target``) within the limits; the locate."""
    sc = core.config.servo
    if not (np.isfinite(float(duration_s)) and 0 < float(duration_s) <= sc.max_track_s):
        raise LimitError(ErrorCode.duration_limit, f"duration_s must be within (0, "
                         f"{sc.max_track_s}] (servo.max_track_s), got {duration_s}")
    st = core.arm.ready_state()
    if not core.camera.is_connected:
        raise UnavailableError(ErrorCode.camera_lost, "the camera is lost: tracking needs it")
    loc = locate(core, 1)
    core.arm.guard.check_goal(st.T_base_tcp, goal(loc.T_base_target), "tracking goal", st)
    return loc
