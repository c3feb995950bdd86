"""``POST /api/v1/track``: follow a moving target with the closed-loop servo (a job).

Operator and PLC roles; ``/stop`` ends it at once, like every job. The cell does the work
(:mod:`cell.actions.track`).
"""

from __future__ import annotations

from typing import Annotated, Any

from fastapi import APIRouter, Depends, Request

from api.auth import Caller, require
from api.http.errors import ERROR_RESPONSES
from api.http.routes.calibration import taught_target_tcp, taught_view
from api.http.schemas import Job, TrackRequest
from cell.service import Cell
from estimator.transforms import T_from_pose

router = APIRouter(prefix="/api/v1", tags=["motion"], responses=ERROR_RESPONSES)


@router.post("/track", response_model=Job)
def track(request: Request, caller: Annotated[Caller, Depends(require("track"))],
          body: TrackRequest) -> dict[str, Any]:
    """Hold the TCP at ``standoff_mm`` from the tool pose on the target while it moves, until
    ``/stop``, ``duration_s`` (capped by ``[servo] max_track_s``) or the target is lost
    (the job fails ``target_lost`` with the arm stopped)."""
    T = None if body.T_target_tcp is None else T_from_pose(body.T_target_tcp.position_mm,
                                                          body.T_target_tcp.rotvec_rad)
    if body.taught is not None:
        T = taught_target_tcp(request, body.taught, given=T is not None)
    cell: Cell = request.app.state.cell
    job = cell.track(caller.label, standoff_mm=body.standoff_mm, T_target_tcp=T,
                     duration_s=body.duration_s, wait=body.wait,
                     wait_timeout_s=body.duration_s + 30.0, mode=body.mode,
                     view=taught_view(request, body.taught, body.mode))
    return job.as_dict()
