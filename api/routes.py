"""Routes under ``/api/v1``. Handlers are thin: parse, authorise, call the Cell, shape JSON.

Handlers are plain ``def`` so FastAPI runs them in its thread pool: cell calls block (moves,
camera waits) and must not stall the event loop that serves /stop and /events.
"""

from __future__ import annotations

import time
from typing import Annotated, Any

from fastapi import APIRouter, Body, Depends, Query, Request, Response
from fastapi.responses import StreamingResponse

from api import overlay
from api.auth import Caller, Read, require
from api.errors import ERROR_RESPONSES
from api.routes_calibration import taught_target_tcp
from api.schemas import (
    ApproachRequest,
    GripperRequest,
    Job,
    JobList,
    JogContinuous,
    JogRequest,
    LocateRequest,
    Me,
    Pose,
    StopRequest,
)
from api.sse import SSE_RESPONSES, sse_response
from api.stop import ReadNow, StopCaller, snapshot_now, stop_now
from cell.hardware import SimWorld
from cell.safety import NotFoundError
from cell.service import Cell
from cell.snapshot import with_age
from estimator.transforms import T_from_pose, pose_dict

router = APIRouter(prefix="/api/v1", responses=ERROR_RESPONSES)
sim_router = APIRouter(prefix="/api/v1/sim", tags=["simulation"], responses=ERROR_RESPONSES)


def cell_of(request: Request) -> Cell:
    cell: Cell = request.app.state.cell
    return cell


def sim_of(request: Request) -> SimWorld:
    sim = cell_of(request).sim
    if sim is None:  # the routes are not mounted then; kept for type narrowing
        raise NotFoundError("not_simulated", "this cell runs on real hardware")
    return sim


@router.get("/health", tags=["status"])
async def health(request: Request) -> dict[str, Any]:
    """Liveness without auth: 200 while the process serves. ``status`` is ``ok`` with every
    device connected, ``degraded`` otherwise, and ``missing`` names the devices that are not
    (the cell reconnects them by itself). From the cell's snapshot: never waits."""
    return dict((await snapshot_now(cell_of(request))).health)


@router.get("/me", response_model=Me, tags=["status"])
def me(caller: Read) -> Me:
    """Who the token belongs to, so a client can disable what its role may not use."""
    return Me(name=caller.name, role=caller.role, permissions=sorted(caller.permissions))


@router.get("/status", tags=["status"], response_class=Response,
            responses={200: {"content": {"application/json": {}},
                             "description": "the cell's snapshot"}})
async def status(request: Request, caller: ReadNow) -> Response:
    """State, robot pose and mode, camera, gripper, current job, last locate, and
    ``snapshot_age_s`` (the snapshot is refreshed at camera rate; reading it never waits on
    a device)."""
    snap = await snapshot_now(cell_of(request))
    return Response(with_age(snap.status_json, snap.age_s()), media_type="application/json",
                    headers={"Cache-Control": "no-store"})


@router.post("/locate", tags=["vision"])
def locate(request: Request, caller: Annotated[Caller, Depends(require("locate"))],
           body: Annotated[LocateRequest | None, Body()] = None) -> dict[str, Any]:
    """Locate the target now: ``T_base_target``, ``T_camera_target`` and quality."""
    cell = cell_of(request)
    loc = cell.locate(caller.label, (body or LocateRequest()).n_frames)
    return loc.as_dict(time.monotonic())


@router.post("/approach", response_model=Job, tags=["motion"])
def approach(request: Request, caller: Annotated[Caller, Depends(require("approach"))],
             body: Annotated[ApproachRequest | None, Body()] = None) -> dict[str, Any]:
    """Start a look-and-move approach job (``wait=true``: answer when it has ended)."""
    b = body or ApproachRequest()
    T = None if b.T_target_tcp is None else T_from_pose(b.T_target_tcp.position_mm,
                                                       b.T_target_tcp.rotvec_rad)
    if b.taught is not None:
        T = taught_target_tcp(request, b.taught, given=T is not None)
    job = cell_of(request).approach(caller.label, standoff_mm=b.standoff_mm,
                                    speed_mm_s=b.speed_mm_s, T_target_tcp=T,
                                    use_last_locate=b.use_last_locate, wait=b.wait)
    return job.as_dict()


@router.get("/jobs", response_model=JobList, tags=["jobs"])
def jobs(request: Request, caller: Read,
         limit: Annotated[int, Query(ge=1, le=500)] = 50) -> dict[str, Any]:
    return {"jobs": [j.as_dict() for j in cell_of(request).jobs.list_jobs(limit)]}


@router.get("/jobs/{job_id}", response_model=Job, tags=["jobs"])
def job(request: Request, caller: Read, job_id: str) -> dict[str, Any]:
    return cell_of(request).job(job_id).as_dict()


@router.get("/audit", tags=["jobs"])
def audit(request: Request, caller: Read,
          limit: Annotated[int, Query(ge=1, le=1000)] = 100) -> dict[str, Any]:
    """The newest audit entries: every command with caller, parameters, outcome, times."""
    return {"entries": [e.as_dict() for e in cell_of(request).jobs.audit_log(limit)]}


@router.post("/jog", tags=["motion"])
def jog(request: Request, caller: Annotated[Caller, Depends(require("jog"))],
        body: Annotated[JogRequest, Body()]) -> dict[str, Any]:
    """A step (``mode: step``, returns when done) or a continuous jog (``mode: continuous``,
    kept alive by ``/jog/heartbeat`` at least every ``deadman_timeout_s``)."""
    cell = cell_of(request)
    if isinstance(body, JogContinuous):
        return cell.jog_start(caller.label, frame=body.frame, linear_mm_s=body.linear_mm_s,
                              angular_deg_s=body.angular_deg_s)
    T = cell.jog_step(caller.label, frame=body.frame, translation_mm=body.translation_mm,
                      rotation_deg=body.rotation_deg, speed_mm_s=body.speed_mm_s)
    return {"T_base_tcp": pose_dict(T)}


@router.post("/jog/heartbeat", tags=["motion"])
def heartbeat(request: Request,
              caller: Annotated[Caller, Depends(require("jog"))]) -> dict[str, Any]:
    return cell_of(request).heartbeat(caller.label)


@router.post("/stop", tags=["motion"])
async def stop(request: Request, caller: StopCaller,
               body: Annotated[StopRequest | None, Body()] = None) -> dict[str, Any]:
    """Always accepted: stops any motion now and cancels the running job.

    Checked and handed over on the event loop (no worker thread) to the cell's own stop
    thread, so no queue of other requests can delay it; ``commanded_monotonic_s`` is when the
    arm adapter was told (host ``time.monotonic()``).
    """
    reason = (body or StopRequest()).reason
    return await stop_now(cell_of(request), caller.label, reason)


@router.post("/gripper", tags=["gripper"])
def gripper(request: Request, caller: Annotated[Caller, Depends(require("gripper"))],
            body: GripperRequest) -> dict[str, Any]:
    return cell_of(request).gripper(caller.label, body.action, body.position_mm,
                                    body.speed_pct, body.force_pct, body.wait)


@router.get("/camera/frame.png", tags=["vision"],
            responses={200: {"content": {"image/png": {}}, "description": "PNG image"}})
def camera_frame(request: Request, caller: Read, overlay_: Annotated[bool, Query(
        alias="overlay", description="draw detections, ids and target axes")] = False
                 ) -> Response:
    frame, result, error = cell_of(request).preview(overlay_)
    age = max(0.0, time.monotonic() - frame.timestamp_s)
    image = overlay.draw(frame.image, frame.camera, result, error, age) if overlay_ \
        else frame.image
    return Response(overlay.png(image), media_type="image/png",
                    headers={"Cache-Control": "no-store", "X-Frame-Age-S": f"{age:.3f}"})


@router.get("/events", tags=["status"], responses=SSE_RESPONSES)
async def events(request: Request, caller: ReadNow,
                 max_events: Annotated[int | None, Query(ge=1, le=100000)] = None
                 ) -> StreamingResponse:
    """Server-sent events: ``state`` (pose and mode at camera rate), ``job``, ``jog``,
    ``locate``, ``stop``. ``max_events`` ends the stream after that many (for scripts)."""
    return sse_response(request, cell_of(request).events.subscribe(), max_events)


@sim_router.get("/truth")
def sim_truth(request: Request, caller: Read) -> dict[str, Any]:
    """Ground truth of the simulated cell: where the target and the TCP really are."""
    sim = sim_of(request)
    return {"T_base_target": pose_dict(sim.true_T_base_target()),
            "T_base_tcp": pose_dict(sim.true_T_base_tcp())}


@sim_router.put("/target")
def sim_target(request: Request, caller: Annotated[Caller, Depends(require("sim_write"))],
               body: Pose) -> dict[str, Any]:
    """Place the simulated target at a pose in the base frame."""
    T = T_from_pose(body.position_mm, body.rotvec_rad)
    sim_of(request).set_target(T)
    return {"T_base_target": pose_dict(T)}
