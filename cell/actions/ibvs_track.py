"""Track in mode ``"ibvs"``: hold the taught view of a target while it moves.

A job like :func:`cell.actions.track.start_track`, with the image-based loop
(:mod:`cell.actions.loop` with its image-based law in ``track`` mode): it runs until ``stop``,
``duration_s`` (capped by ``[servo] max_track_s``) or the loss of the target. The law has no
feed-forward of the target's motion, so a moving target is followed with a lag of
``speed / gain``; it is for slow drifts and for holding a view, the pose-based track for
conveyors. Checked before the job starts, so a
refusal moves nothing.
"""

from __future__ import annotations

from typing import Any

import numpy as np
from numpy.typing import NDArray

from cell.actions.approach import check_ibvs_request, locate
from cell.actions.ibvs import Features
from cell.actions.loop.image import ImageLaw
from cell.actions.loop.runner import ClosedLoop
from cell.core import CellCore
from cell.error_codes import ErrorCode
from cell.errors import LimitError, RefusedError, UnavailableError
from cell.jobs.store import Job
from cell.motion.guard import Motion
from estimator.transforms import pose_dict

Matrix4 = NDArray[np.float64]


def start_ibvs_track(core: CellCore, caller: str, *, standoff_mm: float, duration_s: float,
                     T_target_tcp: Matrix4 | None, view: Features | None, wait: bool = False,
                     wait_timeout_s: float = 120.0) -> Job:
    sc = core.config.servo
    check_ibvs_request(view, standoff_mm)
    if core.frames.is_fixed:
        raise RefusedError(ErrorCode.not_supported, "tracking by IBVS is for a camera on the "
                           "flange (a fixed camera's IBVS drives the tool's plate to a taught "
                           "view: approach)")
    T_tt = (core.config.approach.T_target_tcp.T() if T_target_tcp is None
            else np.asarray(T_target_tcp, dtype=float))
    duration = float(duration_s)
    params = {"standoff_mm": 0.0, "duration_s": duration, "T_target_tcp": pose_dict(T_tt),
              "mode": "ibvs"}

    def check(motion: Motion) -> None:
        if not (np.isfinite(duration) and 0 < duration <= sc.max_track_s):
            raise LimitError(ErrorCode.duration_limit, f"duration_s must be within (0, "
                             f"{sc.max_track_s}] (servo.max_track_s), got {duration_s}")
        st = core.arm.ready_state()
        if not core.camera.is_connected:
            raise UnavailableError(ErrorCode.camera_lost, "the camera is lost: tracking needs it")
        loc = locate(core, 1)
        core.arm.guard.check_goal(st.T_base_tcp, loc.T_base_target @ T_tt, "tracking goal")

    def work(job_id: str, motion: Motion) -> dict[str, Any]:
        assert view is not None
        return ClosedLoop(core, job_id, motion, ImageLaw(core, view, T_tt, "track"),
                          duration_s=duration).run()

    return core.runner.start("track", caller, params, work, check=check, needs_camera=True,
                             wait=wait, wait_timeout_s=wait_timeout_s)
