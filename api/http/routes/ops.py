"""Routes under ``/api/v1`` for running a production day: the cell's alarms
(``Cell.alarms``), camera settings, the image log of failed locates."""

from __future__ import annotations

from typing import Annotated, Any

from fastapi import APIRouter, Body, Depends, Path, Query, Request
from fastapi.responses import FileResponse

from api.auth import Caller, Read, require
from api.http.errors import ERROR_RESPONSES, NOT_FOUND, UNAVAILABLE
from api.http.schemas import (
    SQLITE_MAX_INT,
    Alarm,
    AlarmList,
    CameraSettingsOut,
    CameraSettingsRequest,
    ImageList,
)
from cell.error_codes import ErrorCode
from cell.errors import NotFoundError
from cell.service import Cell

router = APIRouter(prefix="/api/v1", responses=ERROR_RESPONSES)


def _cell(request: Request) -> Cell:
    cell: Cell = request.app.state.cell
    return cell


# -- alarms ----------------------------------------------------------------------------------
@router.get("/alarms", response_model=AlarmList, tags=["alarms"])
def list_alarms(request: Request, caller: Read,
                active: Annotated[bool, Query(description="only unacknowledged")] = False,
                limit: Annotated[int, Query(ge=1, le=500)] = 50,
                offset: Annotated[int, Query(ge=0, le=10_000_000)] = 0) -> dict[str, Any]:
    """Alarms newest first: failed, cancelled and interrupted jobs and faults (protective or
    emergency stop, arm or camera lost, gripper fault). An alarm stays ``active`` until
    acknowledged; alarms survive a restart of the service."""
    items, total, n_active = _cell(request).alarms.list(active, limit, offset)
    return {"alarms": [a.as_dict() for a in items], "active": n_active, "total": total,
            "offset": offset}


@router.post("/alarms/{alarm_id}/ack", response_model=Alarm, tags=["alarms"],
             responses=NOT_FOUND)
def acknowledge_alarm(request: Request,
                      caller: Annotated[Caller, Depends(require("alarm_ack"))],
                      alarm_id: Annotated[int, Path(ge=1, le=SQLITE_MAX_INT, description=(
                          "the alarm's id (a positive 64-bit integer)"))]) -> dict[str, Any]:
    """Acknowledge (operator role; audited). Acknowledging an acknowledged alarm answers it
    unchanged; 404 ``alarm_not_found`` for an unknown id."""
    return _cell(request).alarms.acknowledge(alarm_id, caller.label).as_dict()


# -- camera settings ------------------------------------------------------------------------
@router.get("/camera/settings", response_model=CameraSettingsOut, tags=["vision"],
            responses=UNAVAILABLE)
def get_camera_settings(request: Request, caller: Read) -> dict[str, Any]:
    """Exposure (µs), gain (ISO) and focus (0..255 or "auto") in force; null for a control
    this camera does not have."""
    return _cell(request).camera_settings()


@router.put("/camera/settings", response_model=CameraSettingsOut, tags=["vision"],
            responses=UNAVAILABLE)
def put_camera_settings(request: Request,
                        caller: Annotated[Caller, Depends(require("camera"))],
                        body: Annotated[CameraSettingsRequest, Body()]) -> dict[str, Any]:
    """Change the settings given (operator role; audited). A value the camera does not
    accept is 422 ``invalid_camera_setting`` naming the setting, and nothing changes."""
    return _cell(request).apply_camera_settings(caller.label, exposure_us=body.exposure_us,
                                                iso=body.iso, focus=body.focus)


# -- image log -------------------------------------------------------------------------------
@router.get("/images", response_model=ImageList, tags=["vision"])
def list_images(request: Request, caller: Read,
                limit: Annotated[int, Query(ge=1, le=200)] = 20,
                offset: Annotated[int, Query(ge=0, le=1_000_000)] = 0) -> dict[str, Any]:
    """Frames whose locate failed, newest first, with the reason (``[api] image_log_dir``;
    ``enabled`` is false when it is not set)."""
    log = _cell(request).image_log
    if log is None:
        return {"images": [], "total": 0, "offset": offset, "enabled": False}
    entries, total = log.page(offset, limit)
    for e in entries:
        e["url"] = f"/api/v1/images/{e['name']}.png"
    return {"images": entries, "total": total, "offset": offset, "enabled": True}


@router.get("/images/{name}.png", tags=["vision"], response_class=FileResponse,
            responses={200: {"content": {"image/png": {}}, "description": "the logged frame"},
                       **NOT_FOUND})
def get_image(request: Request, caller: Read, name: str) -> FileResponse:
    """One logged frame as it was seen (PNG, lossless: detections can be re-run on it)."""
    log = _cell(request).image_log
    path = None if log is None else log.image_path(name)
    if path is None:
        raise NotFoundError(ErrorCode.image_not_found, f"no logged image {name!r}")
    return FileResponse(path, media_type="image/png", headers={"Cache-Control": "no-store"})
