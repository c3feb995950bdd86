"""``POST /api/v1/pick``: one command for a whole pick cycle (a job).

Operator and PLC roles; ``/stop`` ends it at once, like every job. The cell does the work
(:mod:`cell.actions.pick`).
"""

from __future__ import annotations

from typing import Annotated, Any

from fastapi import APIRouter, Body, Depends, Request

from api.auth import Caller, require
from api.http.errors import DEVICE_ERRORS, ERROR_RESPONSES, NOT_FOUND
from api.http.schemas import Job, PickRequest
from cell.service import Cell

router = APIRouter(prefix="/api/v1", tags=["motion"], responses=ERROR_RESPONSES)


@router.post("/pick", response_model=Job, responses={**DEVICE_ERRORS, **NOT_FOUND})
def pick(request: Request, caller: Annotated[Caller, Depends(require("pick"))],
         body: Annotated[PickRequest | None, Body()] = None) -> dict[str, Any]:
    """Pick the next part: locate every part in view, approach the chosen one's pre-pick
    pose, grasp along the tool axis, verify the grip, retract, and place it at the taught
    base-frame pose ``place`` if given. The job's result names the part (``part.id``), the
    grip (``grip.verdict``), each phase's seconds (``phases_s``) and, when placed, where the
    part should be (``place.T_base_part_goal``). A missed grasp fails ``grasp_missed`` with
    the gripper open and the arm retracted. Refusals before anything moved are 404 (unknown
    recipe or taught pose), 409, 422 (a pose the arm cannot reach, the leg named) or 503 (no
    gripper, camera lost). ``wait`` as for ``/approach``."""
    b = body or PickRequest()
    cell: Cell = request.app.state.cell
    job = cell.pick(caller.label, recipe=b.recipe, target=b.target, place=b.place,
                    standoff_mm=b.standoff_mm, mode=b.mode, retract=b.retract, wait=b.wait)
    return job.as_dict()
