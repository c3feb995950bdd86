"""Cell configuration: one TOML file, validated strictly; every error names the offending key.

Tables: ``[camera]``, ``[target]`` and ``[robot]`` (``kind`` required), ``[hand_eye]``,
``[tool]``, ``[approach]``, ``[locate]``, ``[servo]``, ``[limits]``, ``[api]``, ``[gripper]``,
``[sim]``, ``[opcua]``, ``[urscript]``, ``[commissioning]``. A config with any real device must
also state ``[limits]``, ``[tool]`` and ``[hand_eye]`` (their defaults suit only the simulated
cell).
Types are strict (``width = "1280"`` is an error, not a coercion), an unknown key is answered
with the closest valid name, and the commissioning checks (:mod:`cell.config.checks`) catch
values in the wrong unit. The device tables (``[camera]``, ``[robot]``, ``[gripper]``) have one
class per ``kind`` (:mod:`cell.config.devices`).
Keys stay stable, because commissioned cells keep their files.
Without a file every command uses the built-in simulated cell (``cell/configs/sim.toml``).
"""

from __future__ import annotations

import json
import tomllib
import typing
from dataclasses import dataclass
from importlib import resources
from pathlib import Path, PurePosixPath
from typing import Any, Literal
from urllib.parse import urlparse

import numpy as np
from numpy.typing import NDArray
from pydantic import BaseModel, ConfigDict, Field, ValidationError, field_validator, model_validator

from cell.config.checks import Problem, check, closest
from cell.config.devices import (
    CameraConfig,
    DeviceConfig,
    GripperConfig,
    NoGripperConfig,
    RobotConfig,
    table_of,
    with_own_keys,
)
from cell.config.strict import Strict
from cell.error_codes import ErrorCode
from cell.errors import CellError
from cell.results.locate import PickOrder
from cell.results.modes import ApproachMode, PoseMode
from estimator import Target
from estimator.target import layout_problem
from estimator.transforms import T_from_pose


class ConfigError(CellError):
    """The configuration file is missing, unreadable or invalid; the message names the key.

    ``problems`` lists every problem found (schema and commissioning checks), each with its key.
    """

    kind = "invalid"

    def __init__(self, message: str, problems: list[Problem] | None = None) -> None:
        super().__init__(ErrorCode.config_invalid, message)
        self.problems = problems if problems is not None else [Problem("", message)]


class DotLayout(BaseModel):
    """Dot centres in the target frame (mm), dot diameter, dark or light dots: the fields a
    target has wherever it is declared (``[target]``, a recipe's targets)."""

    points_mm: list[tuple[float, float, float]] = Field(min_length=4, max_length=100)
    dot_diameter_mm: float = Field(gt=0)
    polarity: Literal["dark", "light"] = "dark"

    @field_validator("points_mm")
    @classmethod
    def _determines_a_pose(cls, v: list[tuple[float, float, float]]) -> list[
            tuple[float, float, float]]:
        problem = layout_problem(v)
        if problem is not None:
            raise ValueError(problem)
        return v

    def model(self) -> Target:
        return Target(self.points_mm, self.dot_diameter_mm, self.polarity)


class TargetConfig(DotLayout, Strict):
    """The cell's target (``[target]``)."""


Vec3 = tuple[float, float, float]
Joints6 = tuple[float, float, float, float, float, float]


class PoseConfig(Strict):
    """A pose in the project's JSON form: position (mm) and rotation vector (rad)."""

    position_mm: Vec3 = (0.0, 0.0, 0.0)
    rotvec_rad: Vec3 = (0.0, 0.0, 0.0)

    def T(self) -> NDArray[np.float64]:
        return T_from_pose(self.position_mm, self.rotvec_rad)


class HandEyeConfig(Strict):
    """The hand-eye calibration result: the camera's pose on the flange (eye-in-hand,
    ``[camera] mount = "hand"``) or in the robot base frame (eye-to-hand, ``mount = "fixed"``).
    Exactly the one the mount needs may be given (checked by :class:`CellConfig`)."""

    T_flange_camera: PoseConfig = PoseConfig()
    T_base_camera: PoseConfig | None = None

    def stated(self, key: str) -> bool:
        """Whether the file gave ``key``; a fixed camera refuses a (non-identity)
        ``T_flange_camera``, since only the mount the camera has may be stated."""
        return key in self.model_fields_set


class ToolConfig(Strict):
    """The tool centre point on the flange; also sent to the controller (set_tcp)."""

    T_flange_tcp: PoseConfig = PoseConfig()


class ApproachConfig(Strict):
    """Look-and-move defaults.

    ``T_target_tcp`` identity means the tool z axis points into the target plate (the target
    frame's +z points into the plate). The observation pose puts the camera straight in front
    of the target centre at ``observe_distance_mm``, looking along the target's +z.
    """

    T_target_tcp: PoseConfig = PoseConfig()
    standoff_mm: float = Field(default=50.0, ge=0)
    speed_mm_s: float = Field(default=150.0, gt=0)
    accel_mm_s2: float = Field(default=600.0, gt=0)
    # under these, a correction is not made: an approach's own estimate stays this far inside
    # a 0.1 mm / 0.05 deg requirement, beside the calibration's error it cannot see
    tolerance_mm: float = Field(default=0.03, gt=0)
    tolerance_deg: float = Field(default=0.02, gt=0)
    max_cycles: int = Field(default=4, ge=1, le=20)
    observe_distance_mm: float = Field(default=300.0, gt=0)
    settle_s: float = Field(default=0.05, ge=0)
    frames_per_locate: int = Field(default=3, ge=1, le=10)  # averaged inside look-and-move
    # POST /approach without "mode" (and OPC UA / XML-RPC's empty mode, the page's first
    # choice). Servo is 3.75x faster at an equal final error (cell bench approach), but on a
    # loaded 2-core host 3-5 of 10 servo runs still end target_lost at the default
    # [servo] lost_after_s (look-and-move: 10 of 10), so look-and-move stays the default
    # until servo holds under load (docs/performance.md, the approach benchmark).
    mode: PoseMode = ApproachMode.look_and_move  # ibvs needs a taught view


class LocateConfig(Strict):
    """Locating every part in view (``POST /locate {"all": true}``): the order the parts are
    given in, and how far a part may lie from where it was seen last and keep its id."""

    order: PickOrder = "nearest_to_camera_axis"
    same_part_mm: float = Field(default=5.0, gt=0)


class ServoConfig(Strict):
    """Closed-loop visual servoing (approach mode "servo" and tracking, :mod:`cell.servoing`).

    The law is ``twist = feed-forward + gain * error`` with the speed capped by
    ``max_speed_mm_s`` / ``max_angular_speed_deg_s`` and by braking room, and its change per
    tick by ``accel_mm_s2`` / ``angular_accel_deg_s2``. Converged: the estimated error under
    ``tolerance_mm`` / ``tolerance_deg`` on ``converge_frames`` consecutive frames, against
    the goal from the mean of at least ``rest_frames`` poses of the target at rest. No pose
    for ``lost_after_s``: the arm stops and the job fails ``target_lost``.
    """

    gain_lin_per_s: float = Field(default=20.0, gt=0, le=50)
    gain_rot_per_s: float = Field(default=20.0, gt=0, le=50)
    # tracking only: integral action on the error (1/s^2), its share capped at a fifth of
    # the speed limits, against the steady lag of an arm slower than commanded
    track_integral_per_s2: float = Field(default=20.0, ge=0, le=500)
    max_speed_mm_s: float = Field(default=250.0, gt=0)
    max_angular_speed_deg_s: float = Field(default=90.0, gt=0)
    accel_mm_s2: float = Field(default=1500.0, gt=0)
    # the rotation's own acceleration (a 90 deg tool turn at 1.5 rad/s^2, UR's speedl rule of
    # one number for both, took >= 2 s alone); capped by limits.max_angular_accel_deg_s2
    angular_accel_deg_s2: float = Field(default=450.0, gt=0)
    stop_decel_mm_s2: float = Field(default=3000.0, gt=0)
    tolerance_mm: float = Field(default=0.05, gt=0)
    tolerance_deg: float = Field(default=0.03, gt=0)
    converge_frames: int = Field(default=4, ge=1, le=100)
    # an approach converges only on a goal from the mean of at least this many poses of the
    # target at rest (cell/servoing/rest_mean.py): one frame's pose turns about the target by
    # ~0.11 mm at the TCP from home, a mean of N frames by that over sqrt(N). To a view taught
    # at home with the mount off, 20 ended 0.032 mm median from the truth (worst 0.050 mm) in
    # 1.35 s; in the realistic world (a frame every 54 ms) 20 took 2.93 s median, 30 3.95 s
    # (docs/performance.md)
    rest_frames: int = Field(default=20, ge=3, le=30)
    lost_after_s: float = Field(default=0.1, gt=0, le=5)  # of camera time (exposures)
    # loss is judged on camera time (cell/servoing/target_loss.py); a pipeline that examines
    # no frame for this long (host time since its newest examined exposure: a stalled camera
    # or estimator) is lost too. Meanwhile the goal is extrapolated for at most
    # max_predict_s past the newest pose, then held.
    stall_after_s: float = Field(default=1.0, gt=0, le=5)
    max_predict_s: float = Field(default=0.5, gt=0, le=5)
    tick_s: float = Field(default=0.008, ge=0.008, le=0.1)  # control period
    watchdog_s: float = Field(default=0.05, gt=0, le=1)  # the arm brakes when ticks stop
    filter_alpha: float = Field(default=0.5, gt=0, le=1)
    filter_beta: float = Field(default=0.1, ge=0, le=1)
    # validation gate: a pose this far from the filter's prediction is not used (a wrong
    # match, a reflection); only poses that pass count as "a pose arrived"
    gate_mm: float = Field(default=30.0, gt=0)
    gate_deg: float = Field(default=10.0, gt=0)
    approach_timeout_s: float = Field(default=30.0, gt=0)
    max_track_s: float = Field(default=600.0, gt=0)  # the cap on a track job's duration_s
    # a track whose estimated error, once under this, is over it in RMS over the last
    # track_lag_s ends tracking_lag with the arm stopped: the cell cannot keep up
    # (cell/servoing/lag.py); 0: off. The estimated error carries the speed times the pose's
    # latency: 11-13 mm RMS at 150 mm/s on a quiet host, 0.26 mm true
    track_lag_mm: float = Field(default=25.0, ge=0)
    track_lag_s: float = Field(default=0.25, gt=0, le=5)


class IbvsConfig(Strict):
    """Image-based servoing (mode "ibvs": :mod:`cell.servoing.ibvs`, :mod:`cell.servoing.image`).

    The law is ``v_c = -lambda L^+ (s - s*)`` on the dots' normalised image points, the gain
    ``lambda(x) = (l0 - linf) exp(-slope x / (l0 - linf)) + linf`` with ``x`` the largest
    feature error (normalised units, ~1/fx per pixel). Speeds and accelerations are the
    ``[servo]`` caps (and ``[limits]``), the gain capped at ``gain_latency_product`` over the
    loop's delay. Converged: over the last ``converge_frames`` frames, the mean image error under
    ``tolerance_px_rms`` / ``tolerance_px_max``, the TCP motion the mean view still asks for
    under ``tolerance_mm`` / ``tolerance_deg``, and the arm nearly still. Fewer than 4 dots
    matched to the taught view for ``[servo] lost_after_s``: the arm stops, ``target_lost``.
    """

    # 6/s at rest, 10/s from ~3 px of image error on (fx 800): measured 1.4 s median from
    # 30 mm / 6 deg against 3.8 s with 2 / 6 / -100, whose gain stayed near 2-3/s over most of
    # the approach (docs/ibvs.md). The settle averages the last frames' noise, so the loop's
    # tail need not: 3/s at rest took 0.45 s longer to the same end (cell bench loops)
    gain_at_zero_per_s: float = Field(default=6.0, gt=0, le=50)
    gain_at_infinity_per_s: float = Field(default=10.0, gt=0, le=50)
    slope_at_zero: float = Field(default=-2000.0, ge=-10000, le=10000)
    # the gain is capped at this over the loop's delay (the view's age, averaged): the loop
    # stays damped whatever latency the camera and the host's load give it
    gain_latency_product: float = Field(default=0.4, gt=0, le=1.5)
    interaction: Literal["current", "desired", "mean"] = "mean"
    # the window's mean image error; the settle's step then crosses only this much of the
    # image, where a dot's pull towards the pixel grid changes little: from 0.04 px away the
    # step read 0.017-0.028 mm RMS wrong at the TCP from home, from 0.005 px 0.005-0.009 mm
    # (docs/ibvs.md)
    tolerance_px_rms: float = Field(default=0.01, gt=0)
    tolerance_px_max: float = Field(default=0.02, gt=0)
    # the TCP motion the window's mean view still asks for (mm / deg); the loop also waits
    # until the arm moves less than half of these within the loop's delay
    tolerance_mm: float = Field(default=0.06, gt=0)
    tolerance_deg: float = Field(default=0.015, gt=0)
    converge_frames: int = Field(default=6, ge=1, le=100)
    # the error of a dot's centre that averaging frames does not remove (px per image
    # coordinate: the pull towards the pixel grid), in the taught view and the view now; the
    # converged result's estimated error includes what it allows at the TCP
    # (cell.servoing.view_bound). The default is for a camera not measured yet; the simulated
    # camera's is 0.0013 px (`cell bench bias`), and cell/configs/sim.toml takes 0.002.
    centroid_bias_px: float = Field(default=0.01, ge=0)
    # move the measured features on by the arm's motion since their exposure (latency
    # compensation; the latency cap then counts the arm state's age only); off by default:
    # measured no faster (250 mm, 30 mm / 6 deg, 5 runs each at load 3-5: median 2.5 s
    # against 1.9 s, the same final error), its tail noisier (docs/ibvs.md)
    predict_motion: bool = False
    # the final settle (cell.servoing.ibvs_settle): after the loop's test, the arm still,
    # ``settle_frames`` frames averaged, one step ``-L^+ e``; up to ``settle_steps`` times,
    # until the step is under ``settle_tolerance_mm`` / ``_deg``. 0 frames: no settle. One
    # frame's view is ~0.10 mm RMS at the TCP from home, so the last window's mean decides the
    # end: a mean of N frames ~0.10 / sqrt(N) mm. 45 frames, once, with a 250-frame teach:
    # the error ~0.018 mm RMS from home, 1.5 s of the approach (docs/performance.md, cell
    # bench loops)
    settle_frames: int = Field(default=45, ge=0, le=100)
    settle_steps: int = Field(default=1, ge=1, le=10)
    settle_tolerance_mm: float = Field(default=0.01, gt=0)
    settle_tolerance_deg: float = Field(default=0.002, gt=0)
    # the loop's last views taken within this of the rest pose count in the settle too, moved
    # on to it by the arm's motion; off by default (0: still frames only). A view a fraction of
    # a pixel away carries its own pull towards the pixel grid, which the weak direction makes
    # ~0.03-0.08 mm at the TCP from home: measured no better than the still frames alone, the
    # gain of ~14 more frames spent on that bias (docs/ibvs.md)
    settle_carry_mm: float = Field(default=0.0, ge=0, le=2.0)
    settle_carry_deg: float = Field(default=0.0, ge=0, le=0.5)
    approach_timeout_s: float = Field(default=30.0, gt=0)


class TeachConfig(Strict):
    """Teaching a pose relative to the target (``POST /teach``): each of the samples a request
    asks for is the mean of ``frames_per_sample`` frames. An approach to a taught pose is no
    better than the teach: one frame's view of the target at 456 mm is ~0.10 mm RMS at the
    TCP, the mean of 250 frames (the default's 5 samples) ~0.006 mm, and the teach takes
    ~8.5 s at 30 fps (docs/performance.md). Every later approach to the pose carries the
    teach's error, and the teach costs no approach any time, so it averages more frames than
    the settle can."""

    frames_per_sample: int = Field(default=50, ge=1, le=100)


class PickConfig(Strict):
    """How a pick grasps, checks its grip and leaves (``[pick]``); a recipe's target may set
    its own grasp speed, retract distance and grip window.

    The pick approaches the pre-pick pose (the standoff), moves blind along the tool axis to
    the grasp pose at ``grasp_speed_mm_s``, closes, and accepts the grip when the gripper
    stopped on an object with the fingers ``grip_min_mm``..``grip_max_mm`` apart. It leaves
    ``retract_mm`` back along the tool axis, and reaches a place pose from
    ``place_clearance_mm`` above it (along the tool axis), where it opens and leaves again.
    """

    grasp_speed_mm_s: float = Field(default=50.0, gt=0)
    retract_mm: float = Field(default=80.0, ge=0, le=500)
    place_clearance_mm: float = Field(default=80.0, ge=0, le=500)
    place_speed_mm_s: float = Field(default=150.0, gt=0)
    grip_min_mm: float = Field(default=1.0, ge=0)
    grip_max_mm: float = Field(default=84.0, gt=0)

    @model_validator(mode="after")
    def _window(self) -> PickConfig:
        if self.grip_min_mm >= self.grip_max_mm:
            raise ValueError("pick.grip_min_mm must be below pick.grip_max_mm")
        return self


class LimitsConfig(Strict):
    """Safety envelope checked before any motion; a refusal moves nothing."""

    workspace_min_mm: Vec3 = (-900.0, -900.0, -100.0)
    workspace_max_mm: Vec3 = (900.0, 900.0, 1000.0)
    max_speed_mm_s: float = Field(default=250.0, gt=0)
    # Slower than this is refused: a speed that rounds to nothing on the wire would leave an
    # arm creeping for hours while the cell has long given up on the move.
    min_speed_mm_s: float = Field(default=1.0, gt=0)
    max_accel_mm_s2: float = Field(default=1500.0, gt=0)
    max_joint_speed_deg_s: float = Field(default=60.0, gt=0, le=360)  # joint moves (home)
    max_joint_accel_deg_s2: float = Field(default=120.0, gt=0)
    max_jog_speed_mm_s: float = Field(default=100.0, gt=0)
    max_jog_speed_deg_s: float = Field(default=30.0, gt=0)
    max_angular_speed_deg_s: float = Field(default=90.0, gt=0)  # streamed (servo) twists
    # a streamed twist's rotation (10.5 rad/s^2; the translation's cap is max_accel_mm_s2):
    # URScript's speedl takes it as its own aRot, which defaults to the linear value
    max_angular_accel_deg_s2: float = Field(default=600.0, gt=0)
    max_jog_step_mm: float = Field(default=200.0, gt=0)  # one jog step, translation
    max_jog_step_deg: float = Field(default=45.0, gt=0)  # one jog step, rotation
    tilt_limit_deg: float = Field(default=60.0, gt=0, le=180)
    max_move_mm: float = Field(default=800.0, gt=0)
    # the arm's state and a target pose older than this are not used; at least 0.5 s: a
    # standing UR arm's state comes every 0.1 s (quiet pushes) and a pose takes ~0.1 s
    max_pose_age_s: float = Field(default=2.0, ge=0.5)
    deadman_timeout_s: float = Field(default=0.2, gt=0, le=0.25)
    # Reach (cell/motion/reach.py): every pose of a move, as the arm's joints will take it,
    # inside the joint range and this far from a singularity: the wrist (joint 5 at 0 or
    # 180 deg), the elbow (joint 3 at 0 or 180 deg: stretched or folded) and the shoulder (the
    # wrist centre's distance from joint 1's axis, in the arm's plane)
    joint_min_deg: Joints6 = (-360.0,) * 6
    joint_max_deg: Joints6 = (360.0,) * 6
    wrist_singularity_margin_deg: float = Field(default=5.0, ge=0, lt=90)
    elbow_singularity_margin_deg: float = Field(default=5.0, ge=0, lt=90)
    shoulder_singularity_margin_mm: float = Field(default=50.0, ge=0)

    @model_validator(mode="after")
    def _box(self) -> LimitsConfig:
        if any(lo >= hi for lo, hi in zip(self.workspace_min_mm, self.workspace_max_mm,
                                          strict=True)):
            raise ValueError("workspace_min_mm must be below workspace_max_mm on every axis")
        if self.min_speed_mm_s > min(self.max_speed_mm_s, self.max_jog_speed_mm_s):
            raise ValueError("min_speed_mm_s must not exceed max_speed_mm_s or "
                             "max_jog_speed_mm_s")
        if any(lo >= hi for lo, hi in zip(self.joint_min_deg, self.joint_max_deg, strict=True)):
            raise ValueError("joint_min_deg must be below joint_max_deg for every joint")
        return self


Role = Literal["viewer", "operator", "plc"]


class TokenConfig(Strict):
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


STATE_PATH_KEYS = ("job_db", "calibration_dir", "image_log_dir")
STATE_DEFAULTS = {"job_db": "jobs.db", "calibration_dir": "calibration",
                  "image_log_dir": "failed-locates"}


class ApiConfig(Strict):
    """Bearer tokens and their roles, and where the service keeps its state.

    ``state_dir`` (absolute) holds everything the service writes: the job and audit database,
    the taught poses beside it, each hand-eye routine's views and the image log of failed
    locates. With it, relative ``job_db`` / ``calibration_dir`` / ``image_log_dir`` are inside
    it and absent ones default to ``jobs.db``, ``calibration`` and ``failed-locates``; the
    loaded config holds the resolved absolute paths. Without it (the simulated cell) relative
    paths are relative to the working directory. The sample tokens are refused on real hardware.
    """

    tokens: list[TokenConfig] = Field(default_factory=list)
    state_dir: str = ""
    job_db: str = "var/cell_jobs.db"
    # Each successful hand-eye routine saves its views (images, flange poses) to a dataset
    # folder here, named after its job; empty: not saved.
    calibration_dir: str = "var/calibration"
    image_log_dir: str = ""  # empty: no image log of failed locates
    image_log_max: int = Field(default=50, ge=1)
    metrics_public: bool = False  # true: /metrics answers without a token (for a scraper)
    # true: POST /api/v1/stop without any token stops too (audited as anonymous@<address>);
    # an invalid token is still refused. STOP is the safe direction: every token may stop.
    anonymous_stop: bool = True

    @model_validator(mode="before")
    @classmethod
    def _inside_state_dir(cls, data: Any) -> Any:
        if not isinstance(data, dict) or not isinstance(data.get("state_dir"), str) \
                or not data["state_dir"]:
            return data
        root = PurePosixPath(data["state_dir"])
        if not root.is_absolute():
            raise ValueError(f"state_dir must be an absolute path, got {str(root)!r}")
        out = dict(data)
        for key in STATE_PATH_KEYS:
            value = out.get(key, STATE_DEFAULTS[key])
            if isinstance(value, str) and value and not PurePosixPath(value).is_absolute():
                out[key] = str(root / value)
        return out

    @field_validator("tokens")
    @classmethod
    def _unique(cls, v: list[TokenConfig]) -> list[TokenConfig]:
        if len({t.token or t.sha256.lower() for t in v}) != len(v):
            raise ValueError("tokens must be unique")
        return v


class SimCameraTruth(Strict):
    """The simulated lens's true intrinsics (px) and Brown-Conrady distortion (k1 k2 p1 p2 k3);
    each unset value comes from the ``world`` preset, apart from what ``[camera]`` believes."""

    fx: float | None = Field(default=None, gt=0)
    fy: float | None = Field(default=None, gt=0)
    cx: float | None = None
    cy: float | None = None
    dist: list[float] | None = None

    @field_validator("dist")
    @classmethod
    def _dist(cls, v: list[float] | None) -> list[float] | None:
        if v is not None and len(v) not in (4, 5):
            raise ValueError(f"dist is k1 k2 p1 p2 [k3]: 4 or 5 values, got {len(v)}")
        return v


class SimConfig(Strict):
    """Ground truth of the simulated cell; used only by the hardware factory and /sim routes.

    ``world``: ``"ideal"`` (the truth is the cell's config: only the estimator errs) or
    ``"realistic"`` (lens and mount differ from the config by typical commissioning-day
    amounts; see docs/simulator.md). Explicit values here win over the preset.
    """

    world: Literal["ideal", "realistic"] = "ideal"
    camera: SimCameraTruth = SimCameraTruth()
    T_base_target: PoseConfig = PoseConfig(position_mm=(-480.0, -130.0, 0.0))
    # The true camera mount; None means the [hand_eye] value is exact.
    T_flange_camera: PoseConfig | None = None
    # The true pose of a fixed camera ([camera] mount = "fixed"); None: [hand_eye] is exact.
    T_base_camera: PoseConfig | None = None
    # A calibration plate (the target's dot layout) clamped to the tool at this pose on the
    # flange, for the eye-to-hand routine; the fixed camera then sees it instead of the
    # work target (which is off the table meanwhile). None: the tool carries no plate.
    T_flange_board: PoseConfig | None = None
    # The simulated tool body that hides what lies behind it from a fixed camera: a cylinder
    # of this radius from the wrist to the TCP (0: the arm is transparent).
    tool_radius_mm: float = Field(default=30.0, ge=0)
    ur_controller: bool = False  # kind="ur": start the simulated controller at robot.host
    # False: it is not running when the service starts (SimWorld.start_controller starts it),
    # as when a cell PC boots before its controller.
    controller_running_at_start: bool = True
    noise_std: float = Field(default=1.0, ge=0)
    blur_sigma_px: float = Field(default=0.8, ge=0)
    # The arm's true geometry: per-joint errors added to the nominal UR5e DH table the
    # controller reports with (joint zero rad, d mm, a mm; 6 values each); None: the preset.
    dh_delta_theta_rad: list[float] | None = None
    dh_delta_d_mm: list[float] | None = None
    dh_delta_a_mm: list[float] | None = None
    # The camera's timing truth: mid-exposure to the frame being available to the cell
    # (latency and its jitter, s), and the error of the frame's timestamp against the true
    # mid-exposure time (a constant offset and a jitter, s); None: the preset.
    camera_latency_s: float | None = Field(default=None, ge=0, le=0.5)
    camera_latency_jitter_s: float | None = Field(default=None, ge=0, le=0.1)
    timestamp_offset_s: float | None = Field(default=None, ge=-0.1, le=0.1)
    timestamp_jitter_s: float | None = Field(default=None, ge=0, le=0.1)
    # The image smeared along the motion during the exposure; None: the preset.
    motion_blur: bool | None = None
    # Frame-to-frame brightness: a random gain (relative std) and light flicker (relative
    # depth at flicker_hz, averaged over each exposure); None: the preset.
    gain_jitter: float | None = Field(default=None, ge=0, le=0.5)
    flicker_depth: float | None = Field(default=None, ge=0, le=1)
    flicker_hz: float = Field(default=100.0, gt=0)
    # The width the simulated fingers close on: of the target (the world's part 0) and of
    # every part placed later without a width of its own (PUT /api/v1/sim/parts).
    part_width_mm: float = Field(default=40.0, gt=0, le=85)

    @field_validator("dh_delta_theta_rad", "dh_delta_d_mm", "dh_delta_a_mm")
    @classmethod
    def _six(cls, v: list[float] | None) -> list[float] | None:
        if v is not None and len(v) != 6:
            raise ValueError(f"one value per joint: 6 values, got {len(v)}")
        return v


SAMPLE_OPCUA_PASSWORDS = frozenset({"sim-viewer", "sim-operator", "sim-plc"})
OpcUaPolicy = Literal["None", "Basic256Sha256"]


class OpcUaUserConfig(Strict):
    """One OPC UA user: a name and password that map to one of the API's roles."""

    name: str = Field(min_length=1)
    password: str = Field(min_length=1)
    role: Role


class OpcUaConfig(Strict):
    """The OPC UA server inside the service (off unless ``enabled``), for cell PLCs.

    ``security_policies``: ``"None"`` and/or ``"Basic256Sha256"`` (Sign and SignAndEncrypt).
    Basic256Sha256 needs a certificate: ``certificate`` (DER or PEM) and ``private_key`` (PEM),
    or, both empty, a self-signed pair generated at the first start into ``opcua/`` beside the
    job database and reused. Only the ``users`` may connect (user name and password; no
    anonymous sessions); each has one of the API's roles. ``trusted_client_certs_dir`` limits
    Basic256Sha256 to the client certificates in it.
    """

    enabled: bool = False
    endpoint: str = "opc.tcp://127.0.0.1:4840"
    namespace: str = "urn:ur-vision-cell"
    security_policies: list[OpcUaPolicy] = Field(
        default_factory=lambda: list[OpcUaPolicy](["Basic256Sha256"]), min_length=1)
    certificate: str = ""
    private_key: str = ""
    users: list[OpcUaUserConfig] = Field(default_factory=list)
    # A folder of trusted client certificates (DER/PEM): with it, a Basic256Sha256 client whose
    # certificate is not in it is refused; empty: any client certificate (users still log in).
    trusted_client_certs_dir: str = ""
    update_period_s: float = Field(default=0.1, gt=0, le=10)  # how often variables refresh

    @field_validator("endpoint")
    @classmethod
    def _endpoint(cls, v: str) -> str:
        url = urlparse(v)
        try:
            port = url.port
        except ValueError as err:
            raise ValueError(f"endpoint {v!r}: {err}") from err
        if url.scheme != "opc.tcp" or not url.hostname or port is None:
            raise ValueError(f"endpoint must look like opc.tcp://HOST:PORT, got {v!r}")
        return v

    @field_validator("users")
    @classmethod
    def _unique_users(cls, v: list[OpcUaUserConfig]) -> list[OpcUaUserConfig]:
        if len({u.name for u in v}) != len(v):
            raise ValueError("user names must be unique")
        return v

    @model_validator(mode="after")
    def _key_pair(self) -> OpcUaConfig:
        if bool(self.certificate) != bool(self.private_key):
            raise ValueError("certificate and private_key go together (both empty: a "
                             "self-signed pair is generated)")
        if self.enabled and not self.users:
            raise ValueError("users must list at least one user when the server is enabled")
        return self


class UrscriptConfig(Strict):
    """The XML-RPC endpoint a PolyScope program calls (``rpc_factory("xmlrpc", URL)``).

    Off while ``xmlrpc_port`` is 0. With ``require_token`` the URL carries one of the
    ``[api] tokens`` (``http://HOST:PORT/<token>/RPC2``) and the call has that token's role;
    without it ``/RPC2`` acts with the ``plc`` role (simulated cells only).
    """

    xmlrpc_port: int = Field(default=0, ge=0, le=65535)
    host: str = Field(default="127.0.0.1", min_length=1)
    require_token: bool = True


class ModbusConfig(Strict):
    """The Modbus TCP server for PLCs without OPC UA (off while ``port`` is 0); unit id 1.

    ``clients``: the addresses (or networks, ``192.168.1.0/24``) that may write commands;
    empty: any. Every other client may still write the stop command. The commands act with
    ``role`` (one of the API's roles). The register map is in docs/plc.md.
    """

    port: int = Field(default=0, ge=0, le=65535)
    host: str = Field(default="127.0.0.1", min_length=1)
    clients: list[str] = Field(default_factory=list)
    role: str = "plc"

    @field_validator("clients")
    @classmethod
    def _networks(cls, v: list[str]) -> list[str]:
        import ipaddress

        for c in v:
            try:
                ipaddress.ip_network(c, strict=False)
            except ValueError as err:
                raise ValueError(f"modbus client {c!r} is not an address or network") from err
        return v


class CheckConfig(Strict):
    """The calibration check against the fixed reference (``[check]``).

    A check whose tool-level error exceeds either tolerance says ``drifted`` and raises the
    ``calibration_drift`` alarm; ``on_drift = "refuse"`` then refuses approaches, tracks and
    picks until the alarm is acknowledged or a calibration is applied. ``every_jobs`` /
    ``every_minutes`` (0: never) schedule checks, run between jobs, never during one. The
    reference is recorded from ``views`` poses tilted up to ``tilt_deg`` about the plate."""

    tolerance_mm: float = Field(default=0.25, gt=0)
    tolerance_deg: float = Field(default=0.1, gt=0)
    on_drift: Literal["alarm", "refuse"] = "alarm"
    every_jobs: int = Field(default=0, ge=0)
    every_minutes: float = Field(default=0.0, ge=0)
    views: int = Field(default=4, ge=3, le=8)
    tilt_deg: float = Field(default=12.0, gt=0, le=30)
    speed_mm_s: float = Field(default=250.0, gt=0)
    frames_per_view: int = Field(default=3, ge=1, le=10)


class RetentionConfig(Strict):
    """How long the cell keeps what it writes (``[retention]``), by age and by size, pruned in
    the background in small batches (:mod:`cell.supervision.retention`).

    Ages in days (0: kept by age forever, the size bounds still apply). ``database_max_mb``
    bounds the job database's used pages: beyond it the oldest jobs go first, then the oldest
    audit rows, then the oldest acknowledged alarms, whatever their age. Active alarms and
    running jobs are never deleted; hand-eye calibration jobs (the evidence of a calibration)
    only by size. ``images_*`` bound the image log of failed locates.
    ``calibration_datasets_keep`` bounds the hand-eye routines' saved views under ``[api]
    calibration_dir`` to the newest N folders and the calibration in use (0: every one)."""

    jobs_days: float = Field(default=180.0, ge=0)
    audit_days: float = Field(default=730.0, ge=0)
    alarms_days: float = Field(default=365.0, ge=0)
    database_max_mb: float = Field(default=4096.0, gt=0)
    images_days: float = Field(default=90.0, ge=0)
    images_max_mb: float = Field(default=1024.0, gt=0)
    calibration_datasets_keep: int = Field(default=20, ge=0)
    period_s: float = Field(default=300.0, gt=0)
    batch_rows: int = Field(default=500, ge=1, le=100_000)


class CommissioningConfig(Strict):
    """Keys whose unusual value is intended: the commissioning checks let them pass."""

    accept: list[str] = Field(default_factory=list)


class CellConfig(BaseModel):
    """The whole file. ``[camera]``, ``[target]`` and ``[robot]`` are required; with any real
    device ``[limits]``, ``[tool]`` and ``[hand_eye]`` are too (checked on the raw file by
    :func:`cell.config.checks.check`); the rest have defaults (no gripper, simulated truth)."""

    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)

    camera: CameraConfig
    target: TargetConfig
    robot: RobotConfig
    hand_eye: HandEyeConfig = HandEyeConfig()
    tool: ToolConfig = ToolConfig()
    approach: ApproachConfig = ApproachConfig()
    locate: LocateConfig = LocateConfig()
    servo: ServoConfig = ServoConfig()
    ibvs: IbvsConfig = IbvsConfig()
    teach: TeachConfig = TeachConfig()
    pick: PickConfig = PickConfig()
    limits: LimitsConfig = LimitsConfig()
    api: ApiConfig = ApiConfig()
    gripper: GripperConfig = NoGripperConfig()
    sim: SimConfig = SimConfig()
    opcua: OpcUaConfig = OpcUaConfig()
    urscript: UrscriptConfig = UrscriptConfig()
    modbus: ModbusConfig = ModbusConfig()
    check: CheckConfig = CheckConfig()
    retention: RetentionConfig = RetentionConfig()
    commissioning: CommissioningConfig = CommissioningConfig()

    @model_validator(mode="after")
    def _mount_matches_hand_eye(self) -> CellConfig:
        he = self.hand_eye
        if self.camera.mount == "fixed":
            if he.T_base_camera is None:
                raise ValueError("hand_eye.T_base_camera is required with camera.mount = "
                                 "\"fixed\" (the fixed camera's pose in the robot base frame)")
            if he.stated("T_flange_camera") and he.T_flange_camera != PoseConfig():
                raise ValueError("hand_eye.T_flange_camera is for a camera on the flange; "
                                 "with camera.mount = \"fixed\" give T_base_camera only")
            if self.sim.T_flange_camera is not None:
                raise ValueError("sim.T_flange_camera is for a camera on the flange; with "
                                 "camera.mount = \"fixed\" use sim.T_base_camera")
        else:
            if he.T_base_camera is not None:
                raise ValueError("hand_eye.T_base_camera is for a fixed camera; with "
                                 "camera.mount = \"hand\" (the default) give T_flange_camera, "
                                 "or set camera.mount = \"fixed\"")
            if self.sim.T_base_camera is not None or self.sim.T_flange_board is not None:
                raise ValueError("sim.T_base_camera and sim.T_flange_board belong to a fixed "
                                 "camera: set camera.mount = \"fixed\"")
        return self

    @property
    def fixed_camera(self) -> bool:
        """The camera is fixed in the cell (eye-to-hand), not on the flange."""
        return self.camera.mount == "fixed"

    def devices(self) -> tuple[DeviceConfig, ...]:
        """The device tables' configs: camera, robot, gripper."""
        return (self.camera, self.robot, self.gripper)

    def has_real_device(self) -> bool:
        """Any device that is real hardware (then the commissioning rules apply)."""
        return any(d.is_hardware(self.sim) for d in self.devices())


SIM_CONFIG_NAME = "sim.toml"

_MISSING_HINTS = {
    "robot": "required table: [robot] with kind = \"ur\" (a UR controller) or \"sim\"",
    "robot.kind": "required: \"ur\" (a UR controller at host) or \"sim\" (the simulated arm)",
}


@dataclass(frozen=True)
class _At:
    """Where a validation error's location is in the file."""

    key: str  # dotted, without the kind pydantic names inside a device table
    model: type[BaseModel] | None  # the config model at the key (None: past the models)
    kinds: dict[str, type[DeviceConfig]]  # at a device table: its kinds' classes by name


def _at(loc: tuple[int | str, ...]) -> _At:
    model: type[BaseModel] | None = CellConfig
    kinds: dict[str, type[DeviceConfig]] = {}
    parts: list[str] = []
    for part in loc:
        if isinstance(part, str) and part in kinds:
            model, kinds = kinds[part], {}
            continue
        parts.append(str(part))
        if isinstance(part, int):
            continue
        field = model.model_fields.get(part) if model is not None else None
        models = _nested_models(field.annotation) if field is not None else []
        model = models[0] if len(models) == 1 else None
        kinds = {m.tag(): m for m in models if issubclass(m, DeviceConfig)} \
            if len(models) > 1 else {}
    return _At(".".join(parts), model, kinds)


def _nested_models(annotation: Any) -> list[type[BaseModel]]:
    if isinstance(annotation, type) and issubclass(annotation, BaseModel):
        return [annotation]
    return [m for arg in typing.get_args(annotation) for m in _nested_models(arg)]


def _either(names: list[str]) -> str:
    quoted = [repr(n) for n in names]
    return quoted[0] if len(quoted) == 1 else f"{', '.join(quoted[:-1])} or {quoted[-1]}"


def _schema_problems(err: ValidationError) -> list[Problem]:
    problems = []
    for e in err.errors():
        loc = tuple(e["loc"])
        at = _at(loc)
        key, msg = at.key, e["msg"]
        if e["type"] == "extra_forbidden":
            model = _at(loc[:-1]).model
            table = table_of(model) if model is not None and issubclass(model, DeviceConfig) \
                else None
            valid = table.keys() if table is not None else \
                list(model.model_fields) if model is not None else []
            hint = closest(str(loc[-1]), valid)
            msg = "unknown key" + (f"; did you mean {hint!r}?" if hint else
                                   (f"; valid keys: {', '.join(valid)}" if valid else ""))
        elif e["type"] == "missing" and key in _MISSING_HINTS:
            msg = _MISSING_HINTS[key]
        elif e["type"] in ("union_tag_invalid", "union_tag_not_found") and at.kinds:
            key = f"{key}.kind"
            expected = _either(list(at.kinds))
            msg = (f"Input should be {expected}" if e["type"] == "union_tag_invalid"
                   else _MISSING_HINTS.get(key, f"required: {expected}"))
        elif isinstance(e.get("input"), str) and e["type"] in ("int_type", "float_type",
                                                                "bool_type"):
            msg += f" (got the string {e['input']!r}: write it without quotes)"
        elif e["type"] == "value_error":
            msg = msg.removeprefix("Value error, ")
            # a table-level check whose message starts with the key it is about: name that key
            first = msg.split(" ", 1)[0]
            if at.model is not None and first.split(".", 1)[0] in at.model.model_fields:
                key = f"{key}.{first}" if key else first
        problems.append(Problem(key, msg))
    return problems


def _format(problems: list[Problem], source: str) -> str:
    return "\n".join([f"invalid configuration in {source}:", *(f"  {p}" for p in problems)])


def parse_config(data: dict[str, Any], source: str = "<config>") -> CellConfig:
    """Validate raw config data: the strict schema, then the commissioning checks; a
    ConfigError lists every problem found, each naming its key."""
    problems: list[Problem] = []
    config = None
    try:
        # Validated as JSON in strict mode: TOML's arrays fill tuples, integers fill floats,
        # and nothing else is coerced ("1280" is not an integer).
        config = CellConfig.model_validate_json(json.dumps(with_own_keys(data), default=str),
                                                strict=True)
    except ValidationError as err:
        problems.extend(_schema_problems(err))
    problems.extend(check(data))
    if problems or config is None:
        raise ConfigError(_format(problems, source), problems)
    return config


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
