"""Routes under ``/api/v1/arm``: home, unlock a protective stop, power.

Home needs the ``home`` permission (operator and PLC: a production cycle homes); unlock and
power need ``recover`` (operator: they want a person at the cell). Audited, refused (409
``busy``) while another motion runs, like every other command; the cell does the work
(:mod:`cell.actions.recovery`).
"""

from __future__ import annotations

from typing import Annotated, Any

from fastapi import APIRouter, Body, Depends, Request
from pydantic import BaseModel, ConfigDict, Field

from api.auth import Caller, require
from api.http.errors import ERROR_RESPONSES
from api.http.schemas import Flag, Job, Num
from cell.service import Cell

router = APIRouter(prefix="/api/v1/arm", tags=["recovery"], responses=ERROR_RESPONSES)
Homer = Annotated[Caller, Depends(require("home"))]
Operator = Annotated[Caller, Depends(require("recover"))]


class HomeRequest(BaseModel):
    model_config = ConfigDict(extra="forbid", json_schema_extra={"examples": [
        {"speed_deg_s": 30.0, "wait": True}]})
    speed_deg_s: Num | None = Field(
        default=None, gt=0, le=360, description="joint speed; default 30 deg/s or the "
        "configured limits.max_joint_speed_deg_s if lower")
    wait: Flag = Field(default=False, description="answer when the job has ended")


class PowerRequest(BaseModel):
    model_config = ConfigDict(extra="forbid", json_schema_extra={"examples": [{"on": True}]})
    on: Flag = Field(description="true: power on and release the brakes; false: power off")


class ArmReply(BaseModel):
    model_config = ConfigDict(json_schema_extra={"examples": [
        {"robot_mode": "RUNNING", "safety": "NORMAL", "ready": True}]})
    robot_mode: str
    safety: str
    ready: bool


class UnlockReply(BaseModel):
    model_config = ConfigDict(json_schema_extra={"examples": [
        {"unlocked": True, "safety": "NORMAL", "ready": True}]})
    unlocked: bool = Field(description="a protective stop was there and is now unlocked")
    safety: str
    ready: bool


def _cell(request: Request) -> Cell:
    cell: Cell = request.app.state.cell
    return cell


@router.post("/home", response_model=Job)
def home(request: Request, caller: Homer,
         body: Annotated[HomeRequest | None, Body()] = None) -> dict[str, Any]:
    """Joint move to ``[robot] home_joints_deg`` through the guard, as a job (``stop``
    cancels it). With ``wait=true`` the answer is the ended job, also when it failed."""
    b = body or HomeRequest()
    return _cell(request).home(caller.label, speed_deg_s=b.speed_deg_s, wait=b.wait).as_dict()


@router.post("/unlock", response_model=UnlockReply,
             responses={409: {"description": "``unlock_too_early``: the controller refuses for "
                              "5 s after the stop (the message says how long is left); or "
                              "``busy``"}})
def unlock(request: Request, caller: Operator) -> dict[str, Any]:
    """Unlock a protective stop (after its cause was cleared) and restart the control."""
    return _cell(request).unlock(caller.label)


@router.post("/power", response_model=ArmReply)
def power(request: Request, caller: Operator, body: PowerRequest) -> dict[str, Any]:
    """Power on and release the brakes, or power off. Answers when the arm is there."""
    return _cell(request).power(caller.label, body.on)
