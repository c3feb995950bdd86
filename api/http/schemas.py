"""Request and response bodies of the HTTP API (pydantic).

Bounds here are the first line of refusals: a malformed or absurd body is a 422 before the
cell sees it. The cell's own safety checks still run on everything that passes.

Parsing is strict wherever a request can move something: a number is a JSON number (an integer
is fine where a float is expected) and a flag is a JSON boolean. ``"10"`` for a number, ``true``
for a number or ``1``/``"yes"`` for a flag are refused (422 naming the field), never coerced.
"""

from __future__ import annotations

from typing import Annotated, Any, Literal

from pydantic import BaseModel, ConfigDict, Field, Strict, StrictBool, model_validator

from cell.actions.approach_rules import MAX_STANDOFF_MM
from cell.error_codes import ErrorCode
from cell.results import (
    ApproachResult,
    HandEyeRoutineResult,
    HomeResult,
    LocateAllResult,
    LocateResult,
    TrackResult,
)
from cell.results.calibration import CalibrationApplied
from cell.results.check import CheckResult, ReferenceResult
from cell.results.modes import ApproachMode, PoseMode, TrackMode
from cell.results.pick import PickResult

# Strict scalars of request bodies: no strings, no booleans as numbers, no numbers as booleans.
Num = Annotated[float, Strict(), Field(allow_inf_nan=False)]
Int = Annotated[int, Strict()]
Flag = StrictBool
Finite = Num
Vec3 = tuple[Finite, Finite, Finite]


# The largest integer SQLite stores (signed 64 bits): every id or count a route hands to a
# database is bounded by it (or less), so a larger one is a 422, never an overflow.
SQLITE_MAX_INT = 2**63 - 1

class _Body(BaseModel):
    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)


class PoseIn(_Body):
    """``{"position_mm": [x, y, z], "rotvec_rad": [rx, ry, rz]}``, the project's pose object."""

    position_mm: tuple[
        Annotated[Num, Field(ge=-1e5, le=1e5)], Annotated[Num, Field(ge=-1e5, le=1e5)],
        Annotated[Num, Field(ge=-1e5, le=1e5)]]
    rotvec_rad: tuple[
        Annotated[Num, Field(ge=-10, le=10)], Annotated[Num, Field(ge=-10, le=10)],
        Annotated[Num, Field(ge=-10, le=10)]]


class ErrorDetail(BaseModel):
    code: ErrorCode = Field(description="stable machine-readable reason (enum)")
    message: str = Field(description="the reason in words, for people")


class ErrorResponse(BaseModel):
    """The body of every error answer."""

    model_config = ConfigDict(json_schema_extra={"examples": [
        {"error": {"code": "busy", "message": "the arm is busy (approach); wait for it to "
                   "finish or stop it"}}]})
    error: ErrorDetail


class LocateRequest(_Body):
    n_frames: Int = Field(default=1, ge=1, le=10, description="frames averaged (not with all)")
    all: Flag = Field(default=False, description="every part in view, as instances")
    recipe: str | None = Field(
        default=None, min_length=1, max_length=64,
        description="with all: the parts of this recipe's targets (name or number) instead "
                    "of the layout in use")


class ApproachRequest(_Body):
    standoff_mm: Num | None = Field(default=None, ge=0, le=MAX_STANDOFF_MM)
    speed_mm_s: Num | None = Field(default=None, gt=0, le=2000)
    T_target_tcp: PoseIn | None = Field(
        default=None, description="tool pose in the target frame; default from config")
    taught: str | None = Field(
        default=None, min_length=1, max_length=64,
        description="use the T_target_tcp taught under this name (POST /teach) instead")
    use_last_locate: Flag = Field(
        default=False, description="start from the last /locate result instead of locating "
        "again (refused when older than limits.max_pose_age_s)")
    mode: ApproachMode | None = Field(
        default=None, description="servo: closed loop on every frame (pose-based); "
        "look_and_move: stop, locate, correct; ibvs: closed loop on the image features of "
        "the view taught under `taught` (image-based; needs `taught`, no standoff); "
        "default: the config's [approach] mode")
    wait: Flag = Field(default=False, description=(
        "false (default): answer 200 at once with the running job; follow it with GET "
        "/jobs/{id} or /events. true: answer 200 when the job has ended, whatever its end "
        "state: a failed or cancelled approach is still 200, with state 'failed' or "
        "'cancelled' and error {code, message} in the job. Refusals before anything moved "
        "are 4xx/5xx as usual. The wait is bounded; a job still running then is answered "
        "with state 'running'."))


class PickRequest(_Body):
    recipe: Annotated[str, Field(min_length=1, max_length=64)] | Int | None = Field(
        default=None, description="a recipe's name or number (its target's layout, taught "
        "pose, standoff, mode and pick values); null: the cell's [target], [approach], [pick]")
    target: str = Field(default="", max_length=64,
                        description="the recipe's target by name; \"\": its first")
    place: str | None = Field(
        default=None, min_length=1, max_length=64,
        description="a pose taught in the base frame (POST /teach with frame \"base\") to "
        "place the part at; null: keep it in the gripper after the retract")
    standoff_mm: Num | None = Field(default=None, ge=0, le=MAX_STANDOFF_MM,
                                    description="the pre-pick pose's distance from the grasp")
    retract: str | None = Field(
        default=None, min_length=1, max_length=64,
        description="a pose taught in the base frame the retract ends at, after the retract "
        "distance along the tool axis; null: the recipe's (retract_taught), else none")
    mode: PoseMode | None = Field(default=None, description="how the pre-pick pose is "
                                  "approached: look_and_move or servo")
    wait: Flag = Field(default=False, description="as for /approach: true answers when the "
                       "pick has ended, whatever its end state")


class TrackRequest(_Body):
    standoff_mm: Num = Field(ge=0, le=MAX_STANDOFF_MM)
    duration_s: Num = Field(gt=0, le=86400, description="capped by [servo] max_track_s")
    T_target_tcp: PoseIn | None = Field(
        default=None, description="tool pose in the target frame; default from config")
    taught: str | None = Field(default=None, min_length=1, max_length=64,
                               description="use the T_target_tcp taught under this name")
    mode: TrackMode = Field(
        default=ApproachMode.servo, description="servo: hold the pose (pose-based); ibvs: hold "
        "the view taught under `taught` (image-based; standoff_mm must be 0)")
    wait: Flag = False


_Vel = Annotated[Num, Field(ge=-1000, le=1000)]
_AngVel = Annotated[Num, Field(ge=-360, le=360)]


class SimTargetRequest(PoseIn):
    """A target pose and, optionally, the drift it starts now (base frame)."""

    velocity_mm_s: tuple[_Vel, _Vel, _Vel] | None = None
    angular_velocity_deg_s: tuple[_AngVel, _AngVel, _AngVel] | None = None


MAX_SIM_PARTS = 64


class SimPartIn(SimTargetRequest):
    """One part: its true pose in the base frame, optionally drifting from now on (base
    frame), its dot layout and the width the simulated fingers close on."""

    layout: str | None = Field(
        default=None, min_length=1, max_length=129,
        description="null: the cell's [target]; \"<recipe>\": that recipe's first target; "
        "\"<recipe>/<target>\": the recipe's named target")
    width_mm: Num | None = Field(default=None, gt=0, le=85,
                                 description="default: [sim] part_width_mm")
    fixed_reference: Flag = Field(
        default=False, description="a plate clamped in the cell (a calibration check's "
        "reference): it does not drift, the gripper never takes it, PUT /sim/faults "
        "reference_delta knocks it")

    @model_validator(mode="after")
    def _reference_stands_still(self) -> SimPartIn:
        moving = any(self.velocity_mm_s or ()) or any(self.angular_velocity_deg_s or ())
        if self.fixed_reference and moving:
            raise ValueError("a fixed_reference does not drift: no velocity_mm_s or "
                             "angular_velocity_deg_s")
        return self


class SimPartsRequest(_Body):
    model_config = ConfigDict(extra="forbid", allow_inf_nan=False, json_schema_extra={
        "examples": [{"parts": [
            {"position_mm": [-480.0, -100.0, 0.0], "rotvec_rad": [3.1416, 0.0, 0.0]},
            {"position_mm": [-330.0, -100.0, 0.0], "rotvec_rad": [3.1416, 0.0, 0.0],
             "layout": "plate-a/main", "velocity_mm_s": [0.0, 10.0, 0.0]}]}]})
    parts: list[SimPartIn] = Field(min_length=1, max_length=MAX_SIM_PARTS,
                                   description="every part of the world, ids 0, 1, ... in order")


_FaultMm = Annotated[Num, Field(ge=-100, le=100)]
_FaultRad = Annotated[Num, Field(ge=-0.5, le=0.5)]
_FaultPx = Annotated[Num, Field(ge=-100, le=100)]


class SimDeltaIn(_Body):
    """A small rigid delta composed on a pose (``T @ delta``): in that pose's own frame."""

    position_mm: tuple[_FaultMm, _FaultMm, _FaultMm] = Field(
        description="each within +-100 mm")
    rotvec_rad: tuple[_FaultRad, _FaultRad, _FaultRad] = Field(
        default=(0.0, 0.0, 0.0), description="each within +-0.5 rad")


class SimLensFaultIn(_Body):
    """The lens's focal length scaled and its principal point moved (a refocus, a shifted
    optic); the distortion stays."""

    focal_scale: Num = Field(default=1.0, ge=0.8, le=1.2,
                             description="true fx and fy over the commissioned ones")
    principal_point_delta_px: tuple[_FaultPx, _FaultPx] = Field(
        default=(0.0, 0.0), description="added to the true cx, cy (px)")


class SimSlipIn(SimDeltaIn):
    """A part slipped where it lies, without the cell knowing."""

    part: Int = Field(default=0, ge=0, lt=MAX_SIM_PARTS,
                      description="its id (0: the target)")


class SimFaultsRequest(_Body):
    model_config = ConfigDict(extra="forbid", allow_inf_nan=False, json_schema_extra={
        "examples": [{"camera_mount_delta": {"position_mm": [1.0, 0.0, 0.0],
                                             "rotvec_rad": [0.0, 0.0, 0.0]}},
                     {"lens": {"focal_scale": 1.003, "principal_point_delta_px": [2.0, -1.0]},
                      "target_slip": {"part": 0, "position_mm": [0.0, 2.0, 0.0]}}]})
    camera_mount_delta: SimDeltaIn | None = Field(
        default=None, description="the camera knocked: its true mount becomes the "
        "commissioned one @ this delta (T_flange_camera, a fixed camera's T_base_camera)")
    lens: SimLensFaultIn | None = None
    reference_delta: SimDeltaIn | None = Field(
        default=None, description="every fixed reference (PUT /sim/parts fixed_reference) "
        "knocked: its placed pose @ this delta")
    target_slip: SimSlipIn | None = Field(
        default=None, description="a part slipped: its placed pose @ this delta, until the "
        "faults are cleared or the part is picked or placed again")


_Lin = Annotated[Num, Field(ge=-1000, le=1000)]
_Ang = Annotated[Num, Field(ge=-360, le=360)]


class JogStep(_Body):
    mode: Literal["step"] = "step"
    frame: Literal["base", "tool"] = "base"
    translation_mm: tuple[_Lin, _Lin, _Lin] = (0.0, 0.0, 0.0)
    rotation_deg: tuple[_Ang, _Ang, _Ang] = (0.0, 0.0, 0.0)
    speed_mm_s: Num | None = Field(default=None, gt=0, le=2000)


class JogContinuous(_Body):
    mode: Literal["continuous"]
    frame: Literal["base", "tool"] = "base"
    linear_mm_s: tuple[_Lin, _Lin, _Lin] = (0.0, 0.0, 0.0)
    angular_deg_s: tuple[_Ang, _Ang, _Ang] = (0.0, 0.0, 0.0)


JogRequest = Annotated[JogStep | JogContinuous, Field(discriminator="mode")]


class GripperRequest(_Body):
    action: Literal["open", "close", "move", "activate"]
    position_mm: Num | None = Field(default=None, ge=0, le=85)
    speed_pct: Num = Field(default=100.0, ge=0, le=100)
    force_pct: Num = Field(default=50.0, ge=0, le=100)
    wait: Flag = True

    @model_validator(mode="after")
    def _position_for_move(self) -> GripperRequest:
        if self.action == "move" and self.position_mm is None:
            raise ValueError("action 'move' needs position_mm")
        return self


class StopRequest(_Body):
    reason: str = Field(default="requested", max_length=200)



# -- responses ---------------------------------------------------------------------------------
# Response models allow extra fields: a newer service may add some, and clients must ignore
# what they do not know.


class _Out(BaseModel):
    model_config = ConfigDict(extra="allow")


def _examples(*examples: dict[str, Any]) -> ConfigDict:
    return ConfigDict(extra="allow", json_schema_extra={"examples": list(examples)})


def _documented(*examples: dict[str, Any]) -> ConfigDict:
    """A cell result's examples in the schema; the result's own config stays (closed)."""
    return ConfigDict(json_schema_extra={"examples": list(examples)})


POSE_EXAMPLE = {"position_mm": [-480.0, -130.0, 350.0], "rotvec_rad": [3.1416, 0.0, 0.0]}


class PoseOut(_Out):
    """A pose: position in mm and rotation vector in rad."""

    model_config = _examples(POSE_EXAMPLE)
    position_mm: list[float]
    rotvec_rad: list[float]


class JobError(_Out):
    code: str = Field(description="an ErrorCode value (see ErrorDetail)")
    message: str


JOB_EXAMPLE = {
    "id": "3f2a9c1b7d4e", "kind": "approach", "caller": "http:plc(plc)",
    "params": {"standoff_mm": 40.0, "speed_mm_s": 150.0},
    "state": "failed", "progress": {"phase": "locate", "cycle": 1, "cycles": []},
    "result": None,
    "error": {"code": "too_few_blobs", "message": "target not located: 2 blobs, need 4"},
    "created_at": 1796200000.0, "ended_at": 1796200002.5}


class _JobFields(_Out):
    """What every job says; ``result`` is set when it succeeded, ``error`` when it failed,
    was cancelled or interrupted."""

    id: str
    caller: str
    params: dict[str, Any]
    state: Literal["running", "succeeded", "failed", "cancelled", "interrupted"]
    progress: dict[str, Any]
    error: JobError | None
    created_at: float = Field(description="UNIX seconds")
    ended_at: float | None


class ApproachJob(_JobFields):
    """An approach; its result by the approach's ``mode`` (look_and_move, servo, ibvs)."""

    model_config = _examples(JOB_EXAMPLE)
    kind: Literal["approach"]
    result: ApproachResult | None


class TrackJob(_JobFields):
    """Tracking; its result by ``mode`` (track: pose-based, ibvs_track: a taught view)."""

    model_config = _examples(JOB_EXAMPLE | {
        "id": "8c1d2e3f4a5b", "kind": "track", "params": {"standoff_mm": 60.0,
                                                          "duration_s": 10.0},
        "state": "running", "progress": {"phase": "track", "t_s": 2.5, "error_mm": 0.4},
        "error": None, "ended_at": None})
    kind: Literal["track"]
    result: TrackResult | None


class HomeJob(_JobFields):
    """The joint move to the configured home pose."""

    model_config = _examples(JOB_EXAMPLE | {
        "id": "5e6f7a8b9c0d", "kind": "home", "params": {"home_joints_deg": [
            0.0, -90.0, 90.0, -90.0, -90.0, 0.0], "speed_deg_s": 30.0},
        "state": "succeeded", "progress": {"phase": "moving"},
        "result": {"joints_deg": [0.0, -90.0, 90.0, -90.0, -90.0, 0.0],
                   "T_base_tcp": POSE_EXAMPLE}, "error": None})
    kind: Literal["home"]
    result: HomeResult | None


class HandEyeJob(_JobFields):
    """The hand-eye routine; its result holds every method's mount, the refinements, the
    residuals and the verdict."""

    model_config = _examples(JOB_EXAMPLE | {
        "id": "1a2b3c4d5e6f", "kind": "hand_eye_calibration", "caller": "http:op(operator)",
        "params": {"views": 12, "tilt_deg": 30.0, "roll_deg": 60.0, "speed_mm_s": 200.0,
                   "method": "auto"},
        "state": "running", "progress": {"stage": "views", "done": 4, "total": 12},
        "error": None, "ended_at": None})
    kind: Literal["hand_eye_calibration"]
    result: HandEyeRoutineResult | None


class PickJob(_JobFields):
    """A pick: the part taken, the grip's verdict, where the part should end, each phase's
    seconds."""

    model_config = _examples(JOB_EXAMPLE | {
        "id": "7b8c9d0e1f2a", "kind": "pick", "params": {"standoff_mm": 50.0,
                                                         "place": "tray-1"},
        "state": "running", "progress": {"phase": "grasp", "phases_s": {
            "locate": 0.21, "approach": 2.4}}, "error": None, "ended_at": None})
    kind: Literal["pick"]
    result: PickResult | None


class ReferenceJob(_JobFields):
    """Recording the calibration reference: its views and the plate's pose."""

    model_config = _examples(JOB_EXAMPLE | {
        "id": "2b3c4d5e6f7a", "kind": "calibration_reference", "params": {"views": 4},
        "state": "running", "progress": {"stage": "views", "done": 1, "total": 4},
        "error": None, "ended_at": None})
    kind: Literal["calibration_reference"]
    result: ReferenceResult | None


class CheckJob(_JobFields):
    """A calibration check: the verdict, the change at the tool, each view's figures."""

    model_config = _examples(JOB_EXAMPLE | {
        "id": "3c4d5e6f7a8b", "kind": "calibration_check", "params": {},
        "state": "running", "progress": {"stage": "views", "done": 2, "total": 4},
        "error": None, "ended_at": None})
    kind: Literal["calibration_check"]
    result: CheckResult | None


# A long-running command, by its ``kind``: each kind's result is its own typed model.
Job = Annotated[ApproachJob | TrackJob | HomeJob | HandEyeJob | PickJob | ReferenceJob
                | CheckJob, Field(discriminator="kind")]


class JobList(_Out):
    model_config = _examples({"jobs": [JOB_EXAMPLE], "total": 1, "offset": 0})
    jobs: list[Job]
    total: int | None = Field(default=None, description="jobs stored (for paging)")
    offset: int = 0


class Me(_Out):
    model_config = _examples({"name": "line-3-plc", "role": "plc",
                              "permissions": ["approach", "gripper", "home", "locate", "pick",
                                              "read", "stop", "track"]})
    name: str
    role: str
    permissions: list[str]


HealthCode = Literal["starting", "arm_disconnected", "camera_lost", "protective_stop",
                     "emergency_stop", "storage", "disk_space", "plc_server_down"]


class HealthReason(BaseModel):
    code: HealthCode = Field(
        description="starting: the service's first connect to the devices (and the arm's "
        "power-on, the gripper's activation) or its PLC servers' start is still running; "
        "arm_disconnected / camera_lost: a device is not "
        "connected (also in `missing`); protective_stop / emergency_stop: the arm is "
        "safety-stopped; storage: the job database cannot be written; disk_space: a file "
        "system the service writes to is nearly full; plc_server_down: a configured PLC server "
        "(OPC UA, XML-RPC, Modbus) could not start (its port taken, a bad certificate)")
    message: str = Field(description="the reason in words, for people")


class Health(_Out):
    model_config = _examples(
        {"status": "ok", "missing": [], "arm_connected": True, "camera_connected": True,
         "reasons": []},
        {"status": "degraded", "missing": [], "arm_connected": True, "camera_connected": True,
         "reasons": [{"code": "protective_stop", "message": "the arm is in a protective stop: "
                      "clear the cause, then unlock it"}]},
        {"status": "degraded", "missing": ["arm"], "arm_connected": False,
         "camera_connected": True,
         "reasons": [{"code": "arm_disconnected", "message": "the arm's controller is not "
                      "connected; the cell reconnects by itself"}]})
    status: Literal["ok", "degraded"] = Field(
        description="ok: every device connected, the arm not safety-stopped, the job database "
        "writable and the disk not near full; degraded: the process serves, `reasons` says "
        "what is wrong")
    missing: list[str] = Field(default_factory=list,
                               description="devices not connected (being reconnected)")
    arm_connected: bool
    camera_connected: bool
    reasons: list[HealthReason] = Field(
        default_factory=list, description="why the status is degraded (empty when ok)")


LOCATED_EXAMPLE = {
    "T_base_target": {"position_mm": [-480.1, -129.9, 0.1], "rotvec_rad": [0.0, 0.0, 0.001]},
    "T_camera_target": {"position_mm": [1.2, -3.4, 350.2], "rotvec_rad": [3.14, 0.0, 0.0]},
    "T_base_tcp": POSE_EXAMPLE,
    "quality": {"rms_px": 0.12, "max_residual_px": 0.2, "ambiguous": False, "converged": True,
                "n_points": 6, "covariance": None, "frame_age_s": 0.05, "n_frames": 1,
                "spread_mm": 0.0, "spread_deg": 0.0},
    "frame_sequence": 1234,
    "consistency": {
        "verdict": "unchecked", "codes": [], "findings": [],
        "reprojection": {"rms_px": [0.12], "max_rms_px": 0.12, "limit_px": 1.0},
        "frame_spread": {"max_mm": 0.0, "max_deg": 0.0, "limit_mm": 0.5, "limit_deg": 0.2},
        "motion": {"target_at_rest": False, "checks": [], "judged": 0,
                   "max_target_moved_mm": None, "max_target_moved_deg": None,
                   "limit_mm": 0.5, "limit_deg": 0.15, "min_arm_motion_mm": 5.0,
                   "min_arm_motion_deg": 2.0}}}


class Located(LocateResult):
    """The locate answer (:class:`cell.results.locate.LocateResult`) with its example."""

    model_config = _documented(LOCATED_EXAMPLE)


LOCATED_ALL_EXAMPLE = {
    "instances": [{
        "id": 3, "layout": "target", "T_base_target": POSE_EXAMPLE,
        "T_camera_target": {"position_mm": [12.0, -8.0, 300.0], "rotvec_rad": [0.0, 0.0, 0.1]},
        "centre_base_mm": [-420.0, -100.0, 0.0],
        "quality": {"rms_px": 0.12, "max_residual_px": 0.2, "ambiguous": False,
                    "converged": True, "identity": "unique", "n_points": 6, "n_dots": 6,
                    "covariance": None},
        "flags": [], "reasons": [], "pickable": True}],
    "unresolved": [{"n_dots": 3, "box_px": [1210.0, 300.0, 1270.0, 380.0],
                    "flags": ["border"],
                    "reason": "3 dot(s) near the image border: a part cut off by it cannot be "
                              "solved"}],
    "order": "nearest_to_camera_axis", "layouts": ["target"], "T_base_tcp": POSE_EXAMPLE,
    "frame_sequence": 1234, "frame_age_s": 0.03}


class LocatedAll(LocateAllResult):
    """The answer of a locate of every part (:class:`cell.results.locate.LocateAllResult`)
    with its example."""

    model_config = _documented(LOCATED_ALL_EXAMPLE)


class RobotStatus(_Out):
    connected: bool
    mode: str | None = None
    safety: str | None = None
    moving: bool | None = None
    protective_stop: bool | None = None
    T_base_tcp: PoseOut | None = None
    joints_deg: list[float] | None = None
    state_age_s: float | None = None
    error: str | None = Field(default=None, description="why the arm cannot be read")


class CameraStatus(_Out):
    connected: bool
    last_frame_age_s: float | None = None


class GripperState(_Out):
    """The gripper's status; ``stale`` when another command holds the line, ``error`` when
    it cannot be read."""

    model_config = _examples({"activated": True, "position_mm": 85.0, "object_detected": False,
                              "moving": False, "fault": ""})
    activated: bool | None = None
    position_mm: float | None = None
    object_detected: bool | None = None
    moving: bool | None = None
    fault: str | None = None
    stale: bool | None = None
    error: str | None = None


class Status(_Out):
    """The cell now: ``state`` is idle, the running motion (approach, jog, ...), or why the
    arm cannot move (disconnected, emergency_stop, protective_stop, not_ready)."""

    model_config = _examples({
        "state": "idle",
        "robot": {"connected": True, "mode": "RUNNING", "safety": "NORMAL", "moving": False,
                  "protective_stop": False, "T_base_tcp": POSE_EXAMPLE,
                  "joints_deg": [0.0, -90.0, 90.0, -90.0, -90.0, 0.0], "state_age_s": 0.004},
        "camera": {"connected": True, "last_frame_age_s": 0.05},
        "gripper": None, "job": None, "last_locate": None})
    state: str
    robot: RobotStatus
    camera: CameraStatus
    gripper: GripperState | None = Field(default=None, description="null: no gripper")
    job: Job | None = Field(default=None, description="the running job, if any")
    last_locate: Located | None = None


class JogStepResult(_Out):
    model_config = _examples({"T_base_tcp": POSE_EXAMPLE})
    T_base_tcp: PoseOut = Field(description="the pose reached")


class JogInfo(_Out):
    model_config = _examples({"jogging": True, "frame": "base", "deadman_timeout_s": 0.2})
    jogging: bool
    frame: Literal["base", "tool"] | None = None
    deadman_timeout_s: float | None = None


class StopResult(_Out):
    """``stopped`` is false only when the arm could not be told to stop (``arm_error``)."""

    model_config = _examples({"stopped": True, "cancelled": "approach",
                              "job_id": "3f2a9c1b7d4e", "arm_error": None})
    stopped: bool
    cancelled: str | None = Field(default=None, description="the motion that was cancelled")
    job_id: str | None = None
    arm_error: str | None = None
    gripper_error: str | None = None  # the gripper was moving and could not be halted


class AuditEntry(_Out):
    model_config = _examples({
        "id": 41, "caller": "anonymous", "command": "POST /api/v1/approach",
        "params": {"status": 401}, "outcome": "refused:unauthorized", "detail": "unknown token",
        "job_id": None, "started_at": 1796200000.0, "ended_at": 1796200000.0})
    id: int
    caller: str
    command: str
    params: dict[str, Any]
    outcome: str = Field(description="ok, refused:<code>, error, or a job's end state")
    detail: str
    job_id: str | None
    started_at: float
    ended_at: float


AUDIT_EXAMPLE = {
    "id": 41, "caller": "anonymous", "command": "POST /api/v1/approach",
    "params": {"status": 401}, "outcome": "refused:unauthorized", "detail": "unknown token",
    "job_id": None, "started_at": 1796200000.0, "ended_at": 1796200000.0}


class AuditLog(_Out):
    model_config = _examples({"entries": [AUDIT_EXAMPLE]})
    entries: list[AuditEntry]


class SimCameraTruthOut(_Out):
    """The simulated lens as it really is: intrinsics (px), Brown-Conrady k1 k2 p1 p2 k3."""

    fx: float
    fy: float
    cx: float
    cy: float
    dist: list[float]
    width: int
    height: int


class SimEffectsOut(_Out):
    """The rest of the simulated world's truth: the arm's true DH errors against the nominal
    table (joint zero rad, d mm, a mm), the camera's latency and timestamp error (s), motion
    blur, and the frame-to-frame gain (relative) and light flicker."""

    dh_delta_theta_rad: list[float]
    dh_delta_d_mm: list[float]
    dh_delta_a_mm: list[float]
    camera_latency_s: float
    camera_latency_jitter_s: float
    timestamp_offset_s: float
    timestamp_jitter_s: float
    motion_blur: bool
    gain_jitter: float
    flicker_depth: float
    flicker_hz: float


SIM_PART_EXAMPLE = {"id": 0, "layout": None, "T_base_part": POSE_EXAMPLE, "held": False,
                    "width_mm": 40.0, "velocity_mm_s": [0.0, 0.0, 0.0], "T_tcp_part": None}


class SimPartOut(_Out):
    """One simulated part's truth now."""

    model_config = _examples(SIM_PART_EXAMPLE)
    id: int = Field(description="its place in the last PUT /sim/parts list (0: the target)")
    layout: str | None = Field(description="as placed (null: the cell's [target])")
    T_base_part: PoseOut
    held: bool = Field(description="the simulated gripper holds it")
    width_mm: float
    velocity_mm_s: list[float] = Field(description="its drift (base frame; 0 while held)")
    T_tcp_part: PoseOut | None = Field(description="where it sits in the fingers (held only)")
    fixed_reference: bool = Field(False, description="a plate clamped in the cell")


class SimParts(_Out):
    model_config = _examples({"parts": [SIM_PART_EXAMPLE]})
    parts: list[SimPartOut]


class SimLensFaultOut(_Out):
    focal_scale: float
    principal_point_delta_px: list[float]


class SimSlipOut(PoseOut):
    part: int


SIM_FAULTS_EXAMPLE = {"camera_mount_delta": {"position_mm": [1.0, 0.0, 0.0],
                                              "rotvec_rad": [0.0, 0.0, 0.0]},
                       "lens": None, "reference_delta": None, "target_slip": None}
SIM_CAMERA_EXAMPLE = {"fx": 1008.0, "fy": 1007.0, "cx": 643.5, "cy": 397.5,
                      "dist": [-0.045, 0.012, 0.0004, -0.0003, 0.0], "width": 1280,
                      "height": 800}


class SimFaultsOut(_Out):
    """The faults in effect (null: none of that kind)."""

    model_config = _examples(SIM_FAULTS_EXAMPLE)
    camera_mount_delta: PoseOut | None
    lens: SimLensFaultOut | None
    reference_delta: PoseOut | None
    target_slip: SimSlipOut | None = Field(
        description="null also once the slipped part was picked or placed again")


class SimFaultsResult(_Out):
    """The faults in effect and the simulated camera's true mount and lens with them."""

    model_config = _examples({"faults": SIM_FAULTS_EXAMPLE, "T_flange_camera": POSE_EXAMPLE,
                              "T_base_camera": None, "camera": SIM_CAMERA_EXAMPLE})
    faults: SimFaultsOut
    T_flange_camera: PoseOut = Field(description="the true mount now (a fixed camera: its "
                                     "T_base_camera)")
    T_base_camera: PoseOut | None = Field(None, description="a fixed camera's true pose now")
    camera: SimCameraTruthOut = Field(description="the true lens now")


class SimTruth(_Out):
    model_config = _examples({
        "T_base_target": POSE_EXAMPLE, "T_base_tcp": POSE_EXAMPLE, "world": "realistic",
        "T_flange_camera": POSE_EXAMPLE, "camera": SIM_CAMERA_EXAMPLE,
        "parts": [SIM_PART_EXAMPLE], "faults": SIM_FAULTS_EXAMPLE})
    T_base_target: PoseOut = Field(description="part 0's true pose")
    T_base_tcp: PoseOut
    world: str
    T_flange_camera: PoseOut
    T_base_camera: PoseOut | None = Field(None, description="a fixed camera's true pose")
    camera: SimCameraTruthOut
    effects: SimEffectsOut
    parts: list[SimPartOut] = Field(description="every part, by id")
    faults: SimFaultsOut = Field(description="PUT /sim/faults in effect: T_flange_camera, "
                                 "camera and the parts above include them")


class SimTarget(_Out):
    model_config = _examples({"T_base_target": POSE_EXAMPLE})
    T_base_target: PoseOut


class Alarm(_Out):
    """A fault or a failed job the operator must see; it stays active until acknowledged."""

    model_config = _examples({
        "id": 7, "code": "too_few_blobs", "source": "job", "job_id": "3f2a9c1b7d4e",
        "message": "approach 3f2a9c1b7d4e failed: target not located: 2 blobs, need 4",
        "raised_at": 1796200002.5, "active": True, "acknowledged_at": None,
        "acknowledged_by": None})
    id: int
    code: str = Field(description="an ErrorCode value, or a fault: protective_stop, "
                      "emergency_stop, arm_disconnected, camera_lost, gripper_fault")
    source: Literal["job", "arm", "camera", "gripper", "calibration", "storage"]
    job_id: str | None
    message: str
    raised_at: float = Field(description="UNIX seconds")
    active: bool = Field(description="true until acknowledged")
    acknowledged_at: float | None
    acknowledged_by: str | None


class AlarmList(_Out):
    model_config = _examples({"alarms": [], "active": 0, "total": 0, "offset": 0})
    alarms: list[Alarm]
    active: int = Field(description="alarms not yet acknowledged")
    total: int = Field(description="alarms matching the query (for paging)")
    offset: int


class CameraSettingsOut(_Out):
    """The settings in force; null for a control this camera does not have."""

    model_config = _examples({"exposure_us": 4000, "iso": 100, "focus": None})
    exposure_us: int | None
    iso: int | None
    focus: int | Literal["auto"] | None


class CameraSettingsRequest(_Body):
    """Settings to change; omitted (or null) ones stay as they are."""

    model_config = ConfigDict(extra="forbid", json_schema_extra={"examples": [
        {"exposure_us": 8000, "iso": 200}]})
    exposure_us: Int | None = Field(default=None, ge=1, le=1_000_000)
    iso: Int | None = Field(default=None, ge=1, le=100_000)
    focus: Annotated[Int, Field(ge=0, le=255)] | Literal["auto"] | None = None


class ImageEntry(_Out):
    model_config = _examples({
        "name": "20261201T120000_000000001_1", "code": "too_few_blobs",
        "message": "target not located: 2 blobs, need 4", "saved_at": 1796200000.0,
        "url": "/api/v1/images/20261201T120000_000000001_1.png"})
    name: str
    code: str | None
    message: str | None
    saved_at: float
    url: str


class ImageList(_Out):
    model_config = _examples({"images": [], "total": 0, "offset": 0, "enabled": True})
    images: list[ImageEntry]
    total: int
    offset: int
    enabled: bool = Field(description="false when [api] image_log_dir is not set")


class ApplyResult(CalibrationApplied):
    """The answer of applying a calibration (:class:`cell.results.calibration.
    CalibrationApplied`) with its example."""

    model_config = _documented({
        "job_id": "3f2a9c1b7d4e", "T_flange_camera": POSE_EXAMPLE, "mount": "hand",
        "transform": "T_flange_camera", "running": True, "written_config": None,
        "config_change": None})


TAUGHT_EXAMPLE = {
    "name": "grasp-a", "frame": "target", "T_target_tcp": {"position_mm": [0.0, 0.0, -20.0],
                                        "rotvec_rad": [0.0, 0.0, 0.0]},
    "samples": 5, "spread_mm": 0.03, "spread_deg": 0.01, "T_base_target": POSE_EXAMPLE,
    "T_base_tcp": POSE_EXAMPLE, "taught_by": "http:op(operator)", "taught_at": 1796200000.0}


class TaughtView(_Out):
    """The view taught: each matched dot's normalised image point (undistorted) and depth."""

    ids: list[int]
    xy: list[tuple[float, float]]
    depth_mm: list[float]


class TaughtPoseOut(_Out):
    """A taught pose, with how it was taught: a tool pose relative to the target (``frame``
    ``target``), or a base-frame pose (``base``: a place pose; no target in it)."""

    model_config = _examples(TAUGHT_EXAMPLE)
    name: str
    frame: Literal["target", "base"]
    T_target_tcp: PoseOut | None = Field(description="null for a base-frame pose")
    samples: int
    spread_mm: float
    spread_deg: float
    T_base_target: PoseOut | None = Field(description="null for a base-frame pose")
    T_base_tcp: PoseOut
    taught_by: str
    taught_at: float
    view: TaughtView | None = Field(
        default=None, description="the desired image features recorded when taught (IBVS "
        "converges on them); null for a pose taught without them")


class TaughtList(_Out):
    model_config = _examples({"taught": [TAUGHT_EXAMPLE]})
    taught: list[TaughtPoseOut]


class TaughtDeleted(_Out):
    model_config = _examples({"deleted": TAUGHT_EXAMPLE})
    deleted: TaughtPoseOut
