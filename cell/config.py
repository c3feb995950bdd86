"""Cell configuration: one TOML file, validated with pydantic; errors name the offending key.

Tables: ``[camera]`` and ``[target]`` (required), ``[robot]``, ``[hand_eye]``, ``[tool]``,
``[approach]``, ``[limits]``, ``[api]``, ``[gripper]``, ``[sim]``. Keys stay stable, because
commissioned cells keep their files.
Without a file every command uses the built-in simulated cell (``cell/configs/sim.toml``).
"""

from __future__ import annotations

import tomllib
from importlib import resources
from pathlib import Path
from typing import Any, Literal

import numpy as np
from numpy.typing import NDArray
from pydantic import BaseModel, ConfigDict, Field, ValidationError, field_validator, model_validator

from estimator import CameraModel, Target
from estimator.transforms import T_from_pose


class ConfigError(Exception):
    """The configuration file is missing, unreadable or invalid; the message names the key."""

    code = "config_invalid"


class _Strict(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)


class CameraConfig(_Strict):
    """Intrinsics for the configured output size (OpenCV model)."""

    fx: float = Field(gt=0)
    fy: float = Field(gt=0)
    cx: float
    cy: float
    width: int = Field(gt=0)
    height: int = Field(gt=0)
    dist: list[float] = Field(default_factory=list)
    # Optional: which device, and its frame rate.
    kind: Literal["sim", "oak"] = "sim"
    fps: float = Field(default=15.0, gt=0, le=120)

    @field_validator("dist")
    @classmethod
    def _dist_len(cls, v: list[float]) -> list[float]:
        if len(v) not in (0, 4, 5, 8, 12, 14):
            raise ValueError("dist must have 0, 4, 5, 8, 12 or 14 coefficients")
        return v

    def model(self) -> CameraModel:
        return CameraModel(self.fx, self.fy, self.cx, self.cy, tuple(self.dist),
                           self.width, self.height)


class TargetConfig(_Strict):
    """Dot centres in the target frame (mm), dot diameter, dark or light dots."""

    points_mm: list[tuple[float, float, float]] = Field(min_length=4, max_length=12)
    dot_diameter_mm: float = Field(gt=0)
    polarity: Literal["dark", "light"] = "dark"

    def model(self) -> Target:
        return Target(self.points_mm, self.dot_diameter_mm, self.polarity)


Vec3 = tuple[float, float, float]


class PoseConfig(_Strict):
    """A pose in the project's JSON form: position (mm) and rotation vector (rad)."""

    position_mm: Vec3 = (0.0, 0.0, 0.0)
    rotvec_rad: Vec3 = (0.0, 0.0, 0.0)

    def T(self) -> NDArray[np.float64]:
        return T_from_pose(self.position_mm, self.rotvec_rad)


class RobotConfig(_Strict):
    """``kind = "ur"``: a UR controller at ``host`` through ur_rtde; ``"sim"``: the in-process
    simulated arm (fast tests). ``home_joints_deg`` is where ``cell serve`` starts on a simulated
    arm and what an operator can return to."""

    kind: Literal["ur", "sim"] = "sim"
    host: str = "127.0.0.1"
    connect_timeout_s: float = Field(default=5.0, gt=0)
    home_joints_deg: tuple[float, float, float, float, float, float] = (
        0.0, -90.0, 90.0, -90.0, -90.0, 0.0)


class HandEyeConfig(_Strict):
    """Eye-in-hand calibration result: the camera's pose on the flange."""

    T_flange_camera: PoseConfig = PoseConfig()


class ToolConfig(_Strict):
    """The tool centre point on the flange; also sent to the controller (set_tcp)."""

    T_flange_tcp: PoseConfig = PoseConfig()


class ApproachConfig(_Strict):
    """Look-and-move defaults.

    ``T_target_tcp`` identity means the tool z axis points into the target plate (the target
    frame's +z points into the plate). The observation pose puts the camera straight in front
    of the target centre at ``observe_distance_mm``, looking along the target's +z.
    """

    T_target_tcp: PoseConfig = PoseConfig()
    standoff_mm: float = Field(default=50.0, ge=0)
    speed_mm_s: float = Field(default=150.0, gt=0)
    accel_mm_s2: float = Field(default=600.0, gt=0)
    tolerance_mm: float = Field(default=0.1, gt=0)
    tolerance_deg: float = Field(default=0.05, gt=0)
    max_cycles: int = Field(default=4, ge=1, le=20)
    observe_distance_mm: float = Field(default=300.0, gt=0)
    settle_s: float = Field(default=0.05, ge=0)
    frames_per_locate: int = Field(default=3, ge=1, le=10)  # averaged inside look-and-move


class LimitsConfig(_Strict):
    """Safety envelope checked before any motion; a refusal moves nothing."""

    workspace_min_mm: Vec3 = (-900.0, -900.0, -100.0)
    workspace_max_mm: Vec3 = (900.0, 900.0, 1000.0)
    max_speed_mm_s: float = Field(default=250.0, gt=0)
    max_accel_mm_s2: float = Field(default=1500.0, gt=0)
    max_jog_speed_mm_s: float = Field(default=100.0, gt=0)
    max_jog_speed_deg_s: float = Field(default=30.0, gt=0)
    max_jog_step_mm: float = Field(default=200.0, gt=0)  # one jog step, translation
    max_jog_step_deg: float = Field(default=45.0, gt=0)  # one jog step, rotation
    tilt_limit_deg: float = Field(default=60.0, gt=0, le=180)
    max_move_mm: float = Field(default=800.0, gt=0)
    max_pose_age_s: float = Field(default=2.0, gt=0)
    deadman_timeout_s: float = Field(default=0.2, gt=0, le=0.25)

    @model_validator(mode="after")
    def _box(self) -> LimitsConfig:
        if any(lo >= hi for lo, hi in zip(self.workspace_min_mm, self.workspace_max_mm,
                                          strict=True)):
            raise ValueError("workspace_min_mm must be below workspace_max_mm on every axis")
        return self


Role = Literal["viewer", "operator", "plc"]


class TokenConfig(_Strict):
    """A token in the clear (``token``), or stored as ``sha256`` = hex sha256 of ``salt`` +
    token (the service then never holds the token itself)."""

    token: str = ""
    role: Role
    name: str = ""
    sha256: str = Field(default="", pattern=r"^([0-9a-fA-F]{64})?$")
    salt: str = ""

    @model_validator(mode="after")
    def _one_secret(self) -> TokenConfig:
        if bool(self.token) == bool(self.sha256):
            raise ValueError("give either token or sha256 (with its salt), not both or none")
        return self


SAMPLE_TOKENS = frozenset({"sim-viewer", "sim-operator", "sim-plc"})


class ApiConfig(_Strict):
    """Bearer tokens and their roles. The sample tokens are refused on real hardware."""

    tokens: list[TokenConfig] = Field(default_factory=list)
    job_db: str = "var/cell_jobs.db"  # relative paths are relative to the working directory
    # Each successful hand-eye routine saves its views (images, flange poses) to a dataset
    # folder here, named after its job; empty: not saved.
    calibration_dir: str = "var/calibration"
    image_log_dir: str = ""  # empty: no image log of failed locates
    image_log_max: int = Field(default=50, ge=1)
    metrics_public: bool = False  # true: /metrics answers without a token (for a scraper)

    @field_validator("tokens")
    @classmethod
    def _unique(cls, v: list[TokenConfig]) -> list[TokenConfig]:
        if len({t.token or t.sha256.lower() for t in v}) != len(v):
            raise ValueError("tokens must be unique")
        return v


class GripperConfig(_Strict):
    """``robotiq``: a 2F-85 compatible gripper on ``port``; ``sim``: the fake one on a pty."""

    kind: Literal["robotiq", "sim", "none"] = "none"
    port: str = ""
    slave_id: int = Field(default=9, ge=1, le=247)


class SimConfig(_Strict):
    """Ground truth of the simulated cell; used only by the hardware factory and /sim routes."""

    T_base_target: PoseConfig = PoseConfig(position_mm=(-480.0, -130.0, 0.0))
    # The true camera mount; None means the [hand_eye] value is exact.
    T_flange_camera: PoseConfig | None = None
    ur_controller: bool = False  # kind="ur": start the simulated controller at robot.host
    noise_std: float = Field(default=1.0, ge=0)
    blur_sigma_px: float = Field(default=0.8, ge=0)
    gripper_object_width_mm: float | None = Field(default=None, ge=0, le=85)


class CellConfig(BaseModel):
    """The whole file. Only ``[camera]`` and ``[target]`` are required, so a minimal file is
    enough for the vision commands; every other table has defaults (simulated arm, no gripper)."""

    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)

    camera: CameraConfig
    target: TargetConfig
    robot: RobotConfig = RobotConfig()
    hand_eye: HandEyeConfig = HandEyeConfig()
    tool: ToolConfig = ToolConfig()
    approach: ApproachConfig = ApproachConfig()
    limits: LimitsConfig = LimitsConfig()
    api: ApiConfig = ApiConfig()
    gripper: GripperConfig = GripperConfig()
    sim: SimConfig = SimConfig()



SIM_CONFIG_NAME = "sim.toml"


def _format_validation_error(err: ValidationError, source: str) -> str:
    lines = [f"invalid configuration in {source}:"]
    for e in err.errors():
        key = ".".join(str(p) for p in e["loc"])
        lines.append(f"  {key}: {e['msg']}")
    return "\n".join(lines)


def parse_config(data: dict[str, Any], source: str = "<config>") -> CellConfig:
    try:
        return CellConfig.model_validate(data)
    except ValidationError as err:
        raise ConfigError(_format_validation_error(err, source)) from err


def load_config(path: str | Path | None = None) -> CellConfig:
    """Load and validate a config file; ``None`` gives the built-in simulated cell."""
    if path is None:
        text = resources.files("cell.configs").joinpath(SIM_CONFIG_NAME).read_text()
        source = f"built-in {SIM_CONFIG_NAME}"
    else:
        p = Path(path)
        try:
            text = p.read_text()
        except OSError as err:
            raise ConfigError(f"cannot read config file {p}: {err.strerror}") from err
        source = str(p)
    try:
        data = tomllib.loads(text)
    except tomllib.TOMLDecodeError as err:
        raise ConfigError(f"{source} is not valid TOML: {err}") from err
    return parse_config(data, source)
