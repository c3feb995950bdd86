"""Request and response bodies of the HTTP API (pydantic).

Bounds here are the first line of refusals: a malformed or absurd body is a 422 before the
cell sees it. The cell's own safety checks still run on everything that passes.
"""

from __future__ import annotations

from typing import Annotated, Any, Literal

from pydantic import BaseModel, ConfigDict, Field, model_validator

Finite = Annotated[float, Field(allow_inf_nan=False)]
Vec3 = tuple[Finite, Finite, Finite]


class _Body(BaseModel):
    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)


class Pose(_Body):
    """``{"position_mm": [x, y, z], "rotvec_rad": [rx, ry, rz]}``, the project's pose object."""

    position_mm: tuple[
        Annotated[float, Field(ge=-1e5, le=1e5)], Annotated[float, Field(ge=-1e5, le=1e5)],
        Annotated[float, Field(ge=-1e5, le=1e5)]]
    rotvec_rad: tuple[
        Annotated[float, Field(ge=-10, le=10)], Annotated[float, Field(ge=-10, le=10)],
        Annotated[float, Field(ge=-10, le=10)]]


class ErrorDetail(BaseModel):
    code: str
    message: str


class ErrorResponse(BaseModel):
    error: ErrorDetail


class LocateRequest(_Body):
    n_frames: int = Field(default=1, ge=1, le=10, description="frames averaged")


class ApproachRequest(_Body):
    standoff_mm: float | None = Field(default=None, ge=0, le=500)
    speed_mm_s: float | None = Field(default=None, gt=0, le=2000)
    T_target_tcp: Pose | None = Field(
        default=None, description="tool pose in the target frame; default from config")
    taught: str | None = Field(
        default=None, min_length=1, max_length=64,
        description="use the T_target_tcp taught under this name (POST /teach) instead")
    use_last_locate: bool = Field(
        default=False, description="start from the last /locate result instead of locating "
        "again (refused when older than limits.max_pose_age_s)")
    mode: Literal["servo", "look_and_move"] | None = Field(
        default=None, description="servo: closed loop on every frame; look_and_move: stop, "
        "locate, correct; default: the config's [approach] mode")
    wait: bool = False


class TrackRequest(_Body):
    standoff_mm: float = Field(ge=0, le=500)
    duration_s: float = Field(gt=0, le=86400, description="capped by [servo] max_track_s")
    T_target_tcp: Pose | None = Field(
        default=None, description="tool pose in the target frame; default from config")
    taught: str | None = Field(default=None, min_length=1, max_length=64,
                               description="use the T_target_tcp taught under this name")
    wait: bool = False


_Vel = Annotated[float, Field(ge=-1000, le=1000)]
_AngVel = Annotated[float, Field(ge=-360, le=360)]


class SimTargetRequest(Pose):
    """A target pose and, optionally, the drift it starts now (base frame)."""

    velocity_mm_s: tuple[_Vel, _Vel, _Vel] | None = None
    angular_velocity_deg_s: tuple[_AngVel, _AngVel, _AngVel] | None = None


_Lin = Annotated[float, Field(ge=-1000, le=1000)]
_Ang = Annotated[float, Field(ge=-360, le=360)]


class JogStep(_Body):
    mode: Literal["step"] = "step"
    frame: Literal["base", "tool"] = "base"
    translation_mm: tuple[_Lin, _Lin, _Lin] = (0.0, 0.0, 0.0)
    rotation_deg: tuple[_Ang, _Ang, _Ang] = (0.0, 0.0, 0.0)
    speed_mm_s: float | None = Field(default=None, gt=0, le=2000)


class JogContinuous(_Body):
    mode: Literal["continuous"]
    frame: Literal["base", "tool"] = "base"
    linear_mm_s: tuple[_Lin, _Lin, _Lin] = (0.0, 0.0, 0.0)
    angular_deg_s: tuple[_Ang, _Ang, _Ang] = (0.0, 0.0, 0.0)


JogRequest = Annotated[JogStep | JogContinuous, Field(discriminator="mode")]


class GripperRequest(_Body):
    action: Literal["open", "close", "move", "activate"]
    position_mm: float | None = Field(default=None, ge=0, le=85)
    speed_pct: float = Field(default=100.0, ge=0, le=100)
    force_pct: float = Field(default=50.0, ge=0, le=100)
    wait: bool = True

    @model_validator(mode="after")
    def _position_for_move(self) -> GripperRequest:
        if self.action == "move" and self.position_mm is None:
            raise ValueError("action 'move' needs position_mm")
        return self


class StopRequest(_Body):
    reason: str = Field(default="requested", max_length=200)


class Job(BaseModel):
    id: str
    kind: str
    caller: str
    params: dict[str, Any]
    state: Literal["running", "succeeded", "failed", "cancelled", "interrupted"]
    progress: dict[str, Any]
    result: dict[str, Any] | None
    error: ErrorDetail | None
    created_at: float
    ended_at: float | None


class JobList(BaseModel):
    jobs: list[Job]


class Me(BaseModel):
    name: str
    role: str
    permissions: list[str]
