"""Routes under ``/api/v1`` for commissioning: the hand-eye routine and taught poses.

Starting, applying, teaching and deleting change the cell, so they need an operator token;
reading needs any token. The calibration service and the taught poses are the cell's
(``Cell.calibration``, ``Cell.taught``).
"""

from __future__ import annotations

from typing import Annotated, Any, Literal

import numpy as np
from fastapi import APIRouter, Body, Depends, Query, Request
from fastapi.responses import StreamingResponse
from numpy.typing import NDArray
from pydantic import BaseModel, ConfigDict, Field

from api.auth import Caller, Read, Stream, require
from api.http.errors import DEVICE_ERRORS, ERROR_RESPONSES, NOT_FOUND
from api.http.media import EventStreamResponse
from api.http.schemas import (
    ApplyResult,
    Flag,
    Int,
    Job,
    JobList,
    Num,
    PoseIn,
    TaughtDeleted,
    TaughtList,
    TaughtPoseOut,
)
from api.http.sse import SSE_RESPONSES, sse_response
from cell.calibration.routine import DEFAULT_VIEWS, RoutineSettings
from cell.calibration.service import EVENT
from cell.error_codes import ErrorCode
from cell.errors import LimitError
from cell.features.teach import (
    DEFAULT_MAX_SPREAD_DEG,
    DEFAULT_MAX_SPREAD_MM,
    NAME_PATTERN,
)
from cell.service import Cell
from cell.servoing.ibvs import Features
from estimator.transforms import T_from_pose

router = APIRouter(prefix="/api/v1", responses={**ERROR_RESPONSES, **NOT_FOUND})

# Calibration and teaching change what every later approach does: the operator's
# permissions (api.auth.PERMISSIONS), not a PLC's.
Calibrator = Annotated[Caller, Depends(require("calibrate"))]
Teacher = Annotated[Caller, Depends(require("teach"))]


class _Body(BaseModel):
    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)


class HandEyeRequest(_Body):
    views: Int = Field(default=DEFAULT_VIEWS, ge=3, le=30,
                       description="views including the start pose")
    tilt_deg: Num = Field(default=30.0, gt=0, le=45,
                            description="camera tilt about the target point")
    roll_deg: Num = Field(default=60.0, ge=0, le=90,
                            description="largest roll about the optical axis")
    speed_mm_s: Num = Field(default=200.0, gt=0, le=2000)
    method: Literal["tsai", "park", "horaud", "joint", "hybrid", "auto"] = Field(
        default="auto", description="the result reported as chosen (all are computed); auto: "
        "joint when it fits within the images' own noise, else hybrid")


class ApplyRequest(_Body):
    method: Literal["tsai", "park", "horaud", "joint", "hybrid", "kinematic"] | None = Field(
        default=None, description="default: the job's chosen method")
    running: Flag = Field(default=True, description="use it in the running cell now")
    write_config: Flag = Field(default=False,
                               description="write it into the config file's [hand_eye] table")
    force: Flag = Field(default=False, description="apply although the verdict says the data "
                        "disagree with themselves")


class TeachRequest(_Body):
    name: str = Field(pattern=NAME_PATTERN.pattern, description="1-64 of [A-Za-z0-9_.-]")
    samples: Int = Field(default=5, ge=1, le=20, description="locates averaged")
    max_spread_mm: Num = Field(default=DEFAULT_MAX_SPREAD_MM, gt=0, le=50)
    max_spread_deg: Num = Field(default=DEFAULT_MAX_SPREAD_DEG, gt=0, le=10)
    replace: Flag = Field(default=True, description="false: refuse if the name is taught")
    frame: Literal["target", "base"] = Field(
        default="target", description="target: the tool pose relative to the located target "
        "(approach to it); base: the resting TCP in the base frame, no camera (a place pose)")


class WaitRequest(_Body):
    wait: Flag = Field(default=False, description="true: answer when the job has ended")


def _cell(request: Request) -> Cell:
    cell: Cell = request.app.state.cell
    return cell


def job_tool_pose(request: Request, taught: str | None, T_target_tcp: PoseIn | None,
                  mode: str | None) -> tuple[NDArray[np.float64] | None, Features | None]:
    """The tool pose and, for ``ibvs``, the view a job request asks for: its ``T_target_tcp``
    or the pose taught under ``taught`` (``Cell.taught.for_job``: 404 for an unknown name,
    422 ``ibvs_needs_taught`` / ``taught_without_view``); 422 when both are given."""
    if taught is not None and T_target_tcp is not None:
        raise LimitError(ErrorCode.invalid_request, "give either T_target_tcp or taught, not both")
    T, view = _cell(request).taught.for_job(taught, mode)
    if T_target_tcp is not None:
        T = T_from_pose(T_target_tcp.position_mm, T_target_tcp.rotvec_rad)
    return T, view


# -- hand-eye --------------------------------------------------------------------------------
@router.post("/calibration/hand-eye", response_model=Job, tags=["calibration"],
             responses=DEVICE_ERRORS)
def start_hand_eye(request: Request, caller: Calibrator,
                   body: Annotated[HandEyeRequest | None, Body()] = None) -> dict[str, Any]:
    """Start the hand-eye routine around the arm's current pose (the target must be in view).
    The arm moves; ``/stop`` cancels it. Poll ``GET .../{id}`` or follow
    ``/calibration/events``."""
    b = body or HandEyeRequest()
    cell = _cell(request)
    limits = cell.config.limits
    settings = RoutineSettings(n_views=b.views, tilt_deg=b.tilt_deg, roll_deg=b.roll_deg,
                               speed_mm_s=b.speed_mm_s,
                               accel_mm_s2=min(4.0 * b.speed_mm_s, limits.max_accel_mm_s2),
                               min_views=min(6, b.views), chosen=b.method)
    return cell.calibration.start(caller.label, settings).as_dict()


@router.get("/calibration/hand-eye/{job_id}", response_model=Job, tags=["calibration"])
def hand_eye_job(request: Request, caller: Read, job_id: str) -> dict[str, Any]:
    """State and progress; when succeeded, ``result`` holds ``T_flange_camera`` per method
    (pose objects), the joint refinement, the residuals and the verdict."""
    return _cell(request).calibration.job(job_id).as_dict()


@router.post("/calibration/hand-eye/{job_id}/apply", response_model=ApplyResult,
             tags=["calibration"], responses=DEVICE_ERRORS)
def apply_hand_eye(request: Request, caller: Calibrator, job_id: str,
                   body: Annotated[ApplyRequest | None, Body()] = None) -> dict[str, Any]:
    """Use the result in the running cell and/or write it into the config file."""
    b = body or ApplyRequest()
    return _cell(request).calibration.apply(caller.label, job_id, b.method, b.running,
                                            b.write_config, b.force).json_dict()


# -- the reference and its check -------------------------------------------------------------
@router.post("/calibration/reference", response_model=Job, tags=["calibration"],
             responses=DEVICE_ERRORS)
def record_reference(request: Request, caller: Calibrator,
                     body: Annotated[WaitRequest | None, Body()] = None) -> dict[str, Any]:
    """Record the calibration reference around the arm's current pose: the plate fixed in the
    cell (the target in use) in view, the arm visits ``[check] views`` poses tilted about it
    and keeps each view's joints and the plate's pose. Do it right after a calibration; the
    check compares against it. ``wait`` as for ``/approach``."""
    return _cell(request).record_reference(caller.label, (body or WaitRequest()).wait).as_dict()


@router.post("/calibration/check", response_model=Job, tags=["calibration"],
             responses=DEVICE_ERRORS)
def check_calibration(request: Request,
                      caller: Annotated[Caller, Depends(require("check_calibration"))],
                      body: Annotated[WaitRequest | None, Body()] = None) -> dict[str, Any]:
    """Check the calibration against the reference: the arm revisits the reference's views
    (joint moves, seconds) and sees the plate again. The result: ``verdict`` (``ok`` /
    ``drifted``), ``tcp_error_mm`` / ``tcp_error_deg`` (the change at the tool), the per-view
    figures. A ``drifted`` check raises the ``calibration_drift`` alarm. 409 ``no_reference``
    before a reference is recorded. ``wait`` as for ``/approach``."""
    return _cell(request).check_calibration(caller.label,
                                            (body or WaitRequest()).wait).as_dict()


@router.get("/calibration/checks", response_model=JobList, tags=["calibration"])
def calibration_checks(request: Request, caller: Read,
                       limit: Annotated[int, Query(ge=1, le=500)] = 100) -> dict[str, Any]:
    """The calibration checks, newest first: how the calibration held over time."""
    jobs = _cell(request).jobs.list_jobs(limit, kind="calibration_check")
    return {"jobs": [j.as_dict() for j in jobs], "total": None, "offset": 0}


@router.get("/calibration/events", tags=["calibration"], responses=SSE_RESPONSES,
            response_class=EventStreamResponse)
async def calibration_events(request: Request, caller: Stream,
                             max_events: Annotated[int | None, Query(ge=1, le=100000)] = None
                             ) -> StreamingResponse:
    """Server-sent ``calibration`` events: progress (stage, done, total), the finished job,
    and applied results. ``max_events`` ends the stream after that many."""
    # The cell's other events have their own stream (/events).
    return sse_response(request, _cell(request).events.subscribe(), max_events,
                        keep=lambda ev: ev["type"] == EVENT)


# -- taught poses ----------------------------------------------------------------------------
@router.post("/teach", response_model=TaughtPoseOut, tags=["teach"],
             responses=DEVICE_ERRORS)
def teach_pose(request: Request, caller: Teacher, body: TeachRequest) -> dict[str, Any]:
    """Store the arm's resting pose under ``name``: with ``frame`` ``target`` its
    ``T_target_tcp`` (``samples`` locates averaged; their spread is reported and over the limit
    refused, 409); with ``base`` the TCP in the base frame (a pick's place pose)."""
    return _cell(request).teach(caller.label, body.name, body.samples, body.max_spread_mm,
                                body.max_spread_deg, body.replace, body.frame).as_dict()


@router.get("/teach", response_model=TaughtList, tags=["teach"])
def list_taught(request: Request, caller: Read) -> dict[str, Any]:
    return {"taught": [p.as_dict() for p in _cell(request).taught.list()]}


@router.get("/teach/{name}", response_model=TaughtPoseOut, tags=["teach"])
def get_taught(request: Request, caller: Read, name: str) -> dict[str, Any]:
    return _cell(request).taught.get(name).as_dict()


@router.delete("/teach/{name}", response_model=TaughtDeleted, tags=["teach"])
def delete_taught(request: Request, caller: Teacher, name: str) -> dict[str, Any]:
    cell = _cell(request)
    pose = cell.taught.delete(name)
    cell.jobs.audit(caller.label, "teach_delete", {"name": name}, "ok")
    return {"deleted": pose.as_dict()}
