"""Routes under ``/api/v1``. Handlers are thin: parse, authorise, call the Cell, shape JSON.

Handlers are plain ``def`` so FastAPI runs them in its thread pool: cell calls block (moves,
camera waits) and must not stall the event loop that serves /stop and /events.
"""

from __future__ import annotations

import asyncio
import dataclasses
import time
from collections.abc import AsyncIterator
from typing import Annotated, Any

import numpy as np
from fastapi import APIRouter, Body, Depends, Query, Request, Response
from fastapi.responses import StreamingResponse
from numpy.typing import NDArray

from api.auth import Caller, Read, Stream, require
from api.http import overlay
from api.http.errors import CONFLICT, DEVICE_ERRORS, ERROR_RESPONSES, NOT_FOUND, UNAVAILABLE
from api.http.live import LiveView
from api.http.media import EventStreamResponse, JPEGResponse, MJPEGResponse, PNGResponse
from api.http.routes.calibration import job_tool_pose
from api.http.schemas import (
    ApproachRequest,
    AuditLog,
    GripperRequest,
    GripperState,
    Health,
    Job,
    JobList,
    JogContinuous,
    JogInfo,
    JogRequest,
    JogStepResult,
    Located,
    LocatedAll,
    LocateRequest,
    Me,
    SimDeltaIn,
    SimFaultsRequest,
    SimFaultsResult,
    SimPartIn,
    SimParts,
    SimPartsRequest,
    SimTarget,
    SimTargetRequest,
    SimTruth,
    Status,
    StopRequest,
    StopResult,
)
from api.http.sse import SSE_RESPONSES, sse_response
from api.http.stop import ReadNow, StopCaller, StreamNow, snapshot_now, stop_now
from api.remote import recipe_ref
from cell.devices.hardware import SimFaults, SimFaultsInEffect, SimPart, SimPartTruth, SimWorld
from cell.error_codes import ErrorCode
from cell.errors import CellError, LimitError, NotFoundError
from cell.service import Cell
from cell.supervision.snapshot import with_age
from estimator.transforms import T_from_pose, pose_dict

router = APIRouter(prefix="/api/v1", responses=ERROR_RESPONSES)
sim_router = APIRouter(prefix="/api/v1/sim", tags=["simulation"], responses=ERROR_RESPONSES)


def cell_of(request: Request) -> Cell:
    cell: Cell = request.app.state.cell
    return cell


def sim_of(request: Request) -> SimWorld:
    sim = cell_of(request).sim
    if sim is None:  # the routes are not mounted then; kept for type narrowing
        raise NotFoundError(ErrorCode.not_simulated, "this cell runs on real hardware")
    return sim


@router.get("/health", response_model=Health, tags=["status"])
async def health(request: Request) -> dict[str, Any]:
    """Liveness without auth: 200 while the process serves, whatever its state. ``status`` is
    ``ok`` with every device connected, the arm not safety-stopped, the job database writable
    and the disk not near full; ``degraded`` otherwise, with ``reasons`` ({code, message}
    each: ``arm_disconnected``, ``camera_lost``, ``protective_stop``, ``emergency_stop``,
    ``storage``, ``disk_space``). ``missing`` names the devices that are not connected (the
    cell reconnects them by itself). From the cell's snapshot: never waits."""
    return dict((await snapshot_now(cell_of(request))).health)


@router.get("/me", response_model=Me, tags=["status"])
def me(caller: Read) -> Me:
    """Who the token belongs to, so a client can disable what its role may not use."""
    return Me(name=caller.name, role=caller.role, permissions=sorted(caller.permissions))


@router.get("/status", tags=["status"], response_class=Response,
            responses={200: {"model": Status, "content": {"application/json": {}},
                             "description": "the cell's snapshot"}})
async def status(request: Request, caller: ReadNow) -> Response:
    """State, robot pose and mode, camera, gripper, current job, last locate, and
    ``snapshot_age_s`` (the snapshot is at most 1.5 camera periods old; reading it never waits on
    a device)."""
    snap = await snapshot_now(cell_of(request))
    return Response(with_age(snap.status_json, snap.age_s()), media_type="application/json",
                    headers={"Cache-Control": "no-store"})


@router.post("/locate", response_model=Located | LocatedAll, tags=["vision"],
             responses={**DEVICE_ERRORS, **NOT_FOUND})
def locate(request: Request, caller: Annotated[Caller, Depends(require("locate"))],
           body: Annotated[LocateRequest | None, Body()] = None) -> dict[str, Any]:
    """Locate the target now: ``T_base_target``, ``T_camera_target`` and quality.

    ``all``: every part in view instead, as ``instances`` (each with its ``id``, stable while
    the part stays put, ``T_base_target``, ``quality``, ``flags`` border/overlap,
    ``pickable``) in the ``[locate] order``, and the dots no layout explains
    (``unresolved``); of the layout in use, or of ``recipe``'s targets (404 for an unknown
    recipe). No part in view is an empty list, not an error."""
    cell = cell_of(request)
    b = body or LocateRequest()
    t0 = time.perf_counter()
    outcome = "error"
    try:
        if b.all:
            parts = cell.locate_all(caller.label, None if b.recipe is None
                                    else recipe_ref(b.recipe))
        else:
            loc = cell.locate(caller.label, b.n_frames)
        outcome = "ok"
    except CellError as err:
        outcome = err.code
        raise
    finally:
        request.app.state.metrics.locate.labels(outcome).observe(time.perf_counter() - t0)
    if b.all:
        return parts.answer(time.monotonic()).json_dict()
    return loc.answer(time.monotonic()).json_dict()


@router.post("/approach", response_model=Job, tags=["motion"],
             responses={**DEVICE_ERRORS, **NOT_FOUND})
def approach(request: Request, caller: Annotated[Caller, Depends(require("approach"))],
             body: Annotated[ApproachRequest | None, Body()] = None) -> dict[str, Any]:
    """Start an approach job, by servoing on every frame or by look-and-move (``mode``;
    default: the config's ``[approach] mode``).

    ``wait=false`` (default): 200 with the running job at once. ``wait=true``: 200 when the
    job has ended, whatever its end state: a failed or cancelled approach is still 200, with
    ``state`` failed/cancelled and ``error`` {code, message}; check ``state``. Refusals
    before anything moved are 404 (unknown taught pose), 409 (busy, protective stop, target
    not located, stale pose), 422 (limits) or 503 (camera lost, arm disconnected)."""
    b = body or ApproachRequest()
    T, view = job_tool_pose(request, b.taught, b.T_target_tcp, b.mode)
    job = cell_of(request).approach(caller.label, standoff_mm=b.standoff_mm,
                                    speed_mm_s=b.speed_mm_s, T_target_tcp=T,
                                    use_last_locate=b.use_last_locate, wait=b.wait,
                                    mode=b.mode, view=view)
    return job.as_dict()


@router.get("/jobs", response_model=JobList, tags=["jobs"])
def jobs(request: Request, caller: Read,
         limit: Annotated[int, Query(ge=1, le=500)] = 50,
         offset: Annotated[int, Query(ge=0, le=10_000_000)] = 0) -> dict[str, Any]:
    """Job history, newest first, ``limit`` per page from ``offset``."""
    store = cell_of(request).jobs
    return {"jobs": [j.as_dict() for j in store.list_jobs(limit, offset)],
            "total": store.count_jobs(), "offset": offset}


@router.get("/jobs/{job_id}", response_model=Job, tags=["jobs"], responses=NOT_FOUND)
def job(request: Request, caller: Read, job_id: str) -> dict[str, Any]:
    """One job (404 ``job_not_found`` for an unknown id)."""
    return cell_of(request).job(job_id).as_dict()


@router.get("/audit", response_model=AuditLog, tags=["jobs"])
def audit(request: Request, caller: Read,
          limit: Annotated[int, Query(ge=1, le=1000)] = 100) -> dict[str, Any]:
    """The newest audit entries: every command with caller, parameters, outcome, times."""
    return {"entries": [e.as_dict() for e in cell_of(request).jobs.audit_log(limit)]}


@router.post("/jog", response_model=JogStepResult | JogInfo, tags=["motion"],
             responses=DEVICE_ERRORS)
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


@router.post("/jog/heartbeat", response_model=JogInfo, tags=["motion"], responses=CONFLICT)
def heartbeat(request: Request,
              caller: Annotated[Caller, Depends(require("jog"))]) -> dict[str, Any]:
    """Keep a continuous jog alive (409 ``not_jogging`` when none runs)."""
    return cell_of(request).heartbeat(caller.label)


@router.post("/stop", response_model=StopResult, tags=["motion"])
async def stop(request: Request, caller: StopCaller,
               body: Annotated[StopRequest | None, Body()] = None) -> dict[str, Any]:
    """Always accepted: stops any motion now and cancels the running job.

    Checked and handed over on the event loop (no worker thread) to the cell's own stop
    thread, so no queue of other requests can delay it; ``commanded_monotonic_s`` is when the
    arm adapter was told (host ``time.monotonic()``).
    """
    reason = (body or StopRequest()).reason
    t0 = time.perf_counter()
    out = await stop_now(cell_of(request), caller.label, reason)
    request.app.state.metrics.stop.observe(time.perf_counter() - t0)
    return out


@router.post("/gripper", response_model=GripperState, tags=["gripper"],
             responses=DEVICE_ERRORS)
def gripper(request: Request, caller: Annotated[Caller, Depends(require("gripper"))],
            body: GripperRequest) -> dict[str, Any]:
    """Open, close, move or activate; answers the gripper's status afterwards (503
    ``gripper_unavailable`` when the cell has none)."""
    return cell_of(request).gripper(caller.label, body.action, body.position_mm,
                                    body.speed_pct, body.force_pct, body.wait)


@router.get("/camera/frame.png", tags=["vision"], response_class=PNGResponse,
            responses={200: {"content": {"image/png": {}}, "description": "PNG image"},
                       **UNAVAILABLE})
def camera_frame(request: Request, caller: Stream, overlay_: Annotated[bool, Query(
        alias="overlay", description="draw detections, ids and target axes")] = False
                 ) -> Response:
    frame, result, error = cell_of(request).preview(overlay_)
    age = max(0.0, time.monotonic() - frame.timestamp_s)
    image = overlay.draw(frame.image, frame.camera, result, error, age) if overlay_ \
        else frame.image
    return Response(overlay.png(image), media_type="image/png",
                    headers={"Cache-Control": "no-store", "X-Frame-Age-S": f"{age:.3f}"})


def live_of(request: Request) -> LiveView:
    live: LiveView = request.app.state.live
    return live


@router.get("/camera/frame.jpg", tags=["vision"], response_class=JPEGResponse,
            responses={200: {"content": {"image/jpeg": {}},
                             "description": "JPEG image; X-Frame-Age-S and X-Frame-Sequence "
                             "headers say how old it is and which camera frame it shows; "
                             "with the overlay, X-Located, X-Locate-Rms-Px, "
                             "X-Locate-Ambiguous and X-Locate-Error what the overlay says"},
                       **UNAVAILABLE})
def camera_frame_jpeg(request: Request, caller: Stream, overlay_: Annotated[bool, Query(
        alias="overlay", description="draw detections, ids and target axes")] = True
                      ) -> Response:
    """The live view: the newest camera frame as JPEG, encoded once and shared by every
    viewer (at most ``LIVE_MAX_FPS`` new frames per second; asking faster repeats one)."""
    live = live_of(request).frame(overlay_)
    age = max(0.0, time.monotonic() - live.timestamp_s)
    return Response(live.jpeg, media_type="image/jpeg",
                    headers={"Cache-Control": "no-store", "X-Frame-Age-S": f"{age:.3f}",
                             "X-Frame-Sequence": str(live.sequence), **live.headers()})


@router.get("/camera/stream.mjpg", tags=["vision"], response_class=MJPEGResponse,
            responses={200: {"content": {"multipart/x-mixed-replace": {}},
                             "description": "MJPEG stream of the live view"}})
async def camera_stream(request: Request, caller: Stream, overlay_: Annotated[bool, Query(
        alias="overlay", description="draw detections, ids and target axes")] = True,
        max_frames: Annotated[int | None, Query(ge=1, le=1_000_000)] = None
                        ) -> StreamingResponse:
    """The live view as an MJPEG stream (for ``<img src>`` or a video client): the same
    shared JPEG frames as ``frame.jpg``; ``max_frames`` ends it after that many."""
    live = live_of(request)
    loop = asyncio.get_running_loop()

    async def parts() -> AsyncIterator[bytes]:
        sent, last_seq = 0, -1
        while max_frames is None or sent < max_frames:
            if await request.is_disconnected():
                break
            try:
                frame = await loop.run_in_executor(None, live.frame, overlay_)
            except CellError:
                await asyncio.sleep(0.5)
                continue
            if frame.sequence == last_seq:
                await asyncio.sleep(live.min_period_s / 2)
                continue
            last_seq = frame.sequence
            sent += 1
            yield (b"--frame\r\nContent-Type: image/jpeg\r\nContent-Length: "
                   + str(len(frame.jpeg)).encode() + b"\r\n\r\n" + frame.jpeg + b"\r\n")

    return StreamingResponse(parts(), media_type="multipart/x-mixed-replace; boundary=frame",
                             headers={"Cache-Control": "no-store"})


@router.get("/events", tags=["status"], responses=SSE_RESPONSES,
            response_class=EventStreamResponse)
async def events(request: Request, caller: StreamNow,
                 max_events: Annotated[int | None, Query(ge=1, le=100000)] = None
                 ) -> StreamingResponse:
    """Server-sent events: ``state`` (pose and mode at camera rate), ``job``, ``jog``,
    ``locate``, ``parts`` (a locate of every part: their ids and poses), ``stop``.
    ``max_events`` ends the stream after that many (for scripts)."""
    return sse_response(request, cell_of(request).events.subscribe(), max_events)


@sim_router.get("/truth", response_model=SimTruth)
def sim_truth(request: Request, caller: Read) -> dict[str, Any]:
    """Ground truth of the simulated cell: where the target (part 0), every part and the TCP
    really are, which part the gripper holds, and the camera's true mount and lens
    (commissioning must recover them; the config may differ)."""
    sim = sim_of(request)
    true = sim.truth_values()
    return {"T_base_target": pose_dict(sim.true_T_base_target()),
            "T_base_tcp": pose_dict(sim.true_T_base_tcp()),
            "world": true.world, **_optics_out(request, sim),
            "effects": dataclasses.asdict(true.effects),
            "parts": [_part_out(p) for p in sim.parts_truth()],
            "faults": _faults_out(sim.faults())}


def _optics_out(request: Request, sim: SimWorld) -> dict[str, Any]:
    """The simulated camera's true mount and lens now."""
    true = sim.truth_values()
    cam = true.camera
    # a simulated fixed camera's mount is its pose in the base frame
    fixed = cell_of(request).config.fixed_camera
    return {"T_flange_camera": pose_dict(true.T_flange_camera),
            "T_base_camera": pose_dict(true.T_flange_camera) if fixed else None,
            "camera": {"fx": cam.fx, "fy": cam.fy, "cx": cam.cx, "cy": cam.cy,
                       "dist": list(cam.dist), "width": cam.width, "height": cam.height}}


def _part_out(part: SimPartTruth) -> dict[str, Any]:
    return {"id": part.id, "layout": part.layout_name, "T_base_part": pose_dict(part.T_base_part),
            "held": part.held, "width_mm": part.width_mm,
            "velocity_mm_s": [float(v) for v in part.velocity_mm_s],
            "T_tcp_part": None if part.T_tcp_part is None else pose_dict(part.T_tcp_part),
            "fixed_reference": part.fixed_reference}


def _faults_out(faults: SimFaultsInEffect) -> dict[str, Any]:
    lens_changed = faults.focal_scale != 1.0 or any(faults.principal_point_delta_px)
    return {
        "camera_mount_delta": (None if faults.T_mount_delta is None
                               else pose_dict(faults.T_mount_delta)),
        "lens": ({"focal_scale": faults.focal_scale,
                  "principal_point_delta_px": list(faults.principal_point_delta_px)}
                 if lens_changed else None),
        "reference_delta": (None if faults.T_reference_delta is None
                            else pose_dict(faults.T_reference_delta)),
        "target_slip": (None if faults.T_slip is None
                        else {"part": faults.slip_part, **pose_dict(faults.T_slip)})}


def _delta(d: SimDeltaIn | None) -> NDArray[np.float64] | None:
    return None if d is None else T_from_pose(d.position_mm, d.rotvec_rad)


@sim_router.put("/faults", response_model=SimFaultsResult)
def sim_faults(request: Request, caller: Annotated[Caller, Depends(require("sim_write"))],
               body: SimFaultsRequest) -> dict[str, Any]:
    """Hurt the simulated cell while it runs, without the cell knowing: knock the camera on
    its mount, shift the lens, knock the fixed reference plates, slip a part. Each is a delta
    on the commissioned truth and replaces whatever faults were set before (a fault not in the
    body is cleared): the body is the whole set. Frames exposed from now on show it; a frame is
    rendered wholly before or after. A fault the world cannot take (no such part, a part in
    the gripper, no fixed reference) is 422 ``invalid_sim_fault`` and changes nothing.
    Answers the faults in effect and the camera's true mount and lens with them
    (docs/simulator.md)."""
    sim = sim_of(request)
    lens, slip = body.lens, body.target_slip
    faults = SimFaults(
        T_mount_delta=_delta(body.camera_mount_delta),
        focal_scale=1.0 if lens is None else lens.focal_scale,
        principal_point_delta_px=(0.0, 0.0) if lens is None else lens.principal_point_delta_px,
        T_reference_delta=_delta(body.reference_delta),
        slip_part=0 if slip is None else slip.part, T_slip=_delta(slip))
    try:
        sim.set_faults(faults)
    except ValueError as err:
        raise LimitError(ErrorCode.invalid_sim_fault, str(err)) from err
    return {"faults": _faults_out(sim.faults()), **_optics_out(request, sim)}


@sim_router.delete("/faults", response_model=SimFaultsResult)
def sim_faults_clear(request: Request,
                     caller: Annotated[Caller, Depends(require("sim_write"))]) -> dict[str, Any]:
    """Clear every fault: the commissioned truth again, exactly (the camera's mount and lens,
    the fixed references and a slipped part where they were)."""
    sim = sim_of(request)
    sim.clear_faults()
    return {"faults": _faults_out(sim.faults()), **_optics_out(request, sim)}


@sim_router.put("/target", response_model=SimTarget)
def sim_target(request: Request, caller: Annotated[Caller, Depends(require("sim_write"))],
               body: SimTargetRequest) -> dict[str, Any]:
    """Place the simulated target (part 0: its layout and width kept, out of the gripper if it
    held it) at a pose in the base frame; with ``velocity_mm_s`` and ``angular_velocity_deg_s``
    (base frame) it drifts from now on, like a conveyor. The other parts stay where they
    are."""
    T = T_from_pose(body.position_mm, body.rotvec_rad)
    v = None if body.velocity_mm_s is None else np.asarray(body.velocity_mm_s, dtype=float)
    w = (None if body.angular_velocity_deg_s is None
         else np.radians(np.asarray(body.angular_velocity_deg_s, dtype=float)))
    try:
        sim_of(request).set_target(T, v, w)
    except ValueError as err:  # a fixed reference asked to drift
        raise LimitError(ErrorCode.invalid_request, str(err)) from err
    return {"T_base_target": pose_dict(T),
            "velocity_mm_s": list(body.velocity_mm_s or (0.0, 0.0, 0.0)),
            "angular_velocity_deg_s": list(body.angular_velocity_deg_s or (0.0, 0.0, 0.0))}


@sim_router.put("/parts", response_model=SimParts)
def sim_parts(request: Request, caller: Annotated[Caller, Depends(require("sim_write"))],
              body: SimPartsRequest) -> dict[str, Any]:
    """Replace the simulated world's parts: each at a pose in the base frame, drifting from
    now on at its velocities (base frame) like a conveyor, with a dot layout (null: the cell's
    ``[target]``; ``"<recipe>"`` or ``"<recipe>/<target>"``: a recipe's target) and a width
    the fingers close on. Ids follow the list (0: the target of ``/sim/target`` and
    ``/locate``'s truth); the gripper holds none of them afterwards. The camera renders every
    part in view; the simulated gripper closing at a part's grasp pose picks it
    (docs/simulator.md). An unknown recipe or target is 404, nothing placed."""
    cell = cell_of(request)
    parts = [_sim_part(cell, p) for p in body.parts]
    sim = sim_of(request)
    sim.place_parts(parts)
    return {"parts": [_part_out(p) for p in sim.parts_truth()]}


def _sim_part(cell: Cell, part: SimPartIn) -> SimPart:
    if part.layout is None:
        layout = cell.config.target.model()
    else:
        recipe, _, target = part.layout.partition("/")
        layout = cell.recipes.get(recipe).target(target).model()
    w = (None if part.angular_velocity_deg_s is None
         else np.radians(np.asarray(part.angular_velocity_deg_s, dtype=float)))
    return SimPart(part.layout, layout, T_from_pose(part.position_mm, part.rotvec_rad),
                   None if part.velocity_mm_s is None else np.asarray(part.velocity_mm_s,
                                                                       dtype=float),
                   w, part.width_mm, part.fixed_reference)
