"""``POST /api/v1/track``: follow a moving target with the closed-loop servo (a job).

Operator and PLC roles; ``/stop`` ends it at once, like every job. The cell does the work
(:mod:`cell.actions.track`).
"""

from __future__ import annotations

from typing import Annotated, Any

from fastapi import APIRouter, Depends, Request

from api.auth import Caller, require
from api.http.errors import ERROR_RESPONSES
from api.http.routes.calibration import job_tool_pose
from api.http.schemas import Job, TrackRequest
from cell.service import Cell

router = APIRouter(prefix="/api/v1", tags=["motion"], responses=ERROR_RESPONSES)


@router.post("/track", response_model=Job)
def track(request: Request, caller: Annotated[Caller, Depends(require("track"))],
          body: TrackRequest) -> dict[str, Any]:
    """Hold the TCP at ``standoff_mm`` from the tool pose on the target while it moves, until
    ``/stop``, ``duration_s`` (capped by ``[servo] max_track_s``) or the target is lost
    (the job fails ``target_lost`` with the arm stopped)."""
    T, view = job_tool_pose(request, body.taught, body.T_target_tcp, body.mode)
    cell: Cell = request.app.state.cell
    job = cell.track(caller.label, standoff_mm=body.standoff_mm, T_target_tcp=T,
                     duration_s=body.duration_s, wait=body.wait,
                     wait_timeout_s=body.duration_s + 30.0, mode=body.mode, view=view)
    return job.as_dict()
