"""The device tables ``[camera]``, ``[robot]`` and ``[gripper]``: one config class per kind.

A table's ``kind`` picks its class; the class holds the keys that kind needs and says whether
such a device is real hardware (:meth:`DeviceConfig.is_hardware`), the one rule the schema's
:meth:`~cell.config.schema.CellConfig.has_real_device` and the commissioning checks on the raw
file both use. What builds each kind is in :mod:`cell.devices.factory`, the one place that may
import the device adapters and the simulated devices.

A kind left out means ``"sim"`` for the camera and ``"none"`` for the gripper; the robot's is
required, so a file that lost it does not run a simulated arm. A key that only another kind of
the same table uses is left out before the file is validated (:func:`with_own_keys`): switching a
device's kind is one edit, and the keys of the other kind wait unused for the day it returns.

Adding a kind: its class here, in its table's union below, and its builder in
``cell/devices/factory.py`` (docs/architecture.md, "Adding a device").
"""

from __future__ import annotations

import typing
from abc import abstractmethod
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Annotated, Any, Literal, Protocol

from pydantic import Field, field_validator, model_validator

from cell.config.strict import Strict
from estimator import CameraModel


class SimStandIns(Protocol):
    """What the ``[sim]`` table runs in place of a configured device."""

    @property
    def ur_controller(self) -> bool:
        """The simulated UR controller serves ``[robot] host``."""
        ...


class DeviceConfig(Strict):
    """One kind of device: its ``kind``, the keys it needs, and whether it is real hardware."""

    @classmethod
    @abstractmethod
    def is_hardware(cls, sim: SimStandIns) -> bool:
        """Whether a device of this kind is a physical one in a cell whose ``[sim]`` table
        is ``sim`` (then the commissioning rules for real hardware apply)."""

    @classmethod
    def tag(cls) -> str:
        """The ``kind`` that names this class in its table."""
        return str(cls.model_fields["kind"].default)


# -- [camera] -----------------------------------------------------------------------------------
class CameraConfigBase(DeviceConfig):
    """Intrinsics for the configured output size (OpenCV model), the mount, the frame rate and
    the sensor settings every camera kind takes."""

    fx: float = Field(gt=0)
    fy: float = Field(gt=0)
    cx: float
    cy: float
    width: int = Field(gt=0)
    height: int = Field(gt=0)
    dist: list[float] = Field(default_factory=list)
    # Which intrinsics the cell computes with: these ("config": a commissioning calibration
    # written here must win) or the ones the device reports with each frame ("device": an
    # OAK's factory calibration). cell.vision.intrinsics.
    intrinsics: Literal["config", "device"] = "config"
    # Where the camera is: on the flange ("hand", eye-in-hand; [hand_eye] T_flange_camera) or
    # fixed in the cell ("fixed", eye-to-hand; [hand_eye] T_base_camera).
    mount: Literal["hand", "fixed"] = "hand"
    # The output size is ``width`` x ``height``. Unset sensor settings keep the device's
    # defaults.
    fps: float = Field(default=15.0, gt=0, le=120)
    exposure_us: int | None = Field(default=None, ge=1)  # manual exposure time
    iso: int | None = Field(default=None, ge=100, le=1600)  # sensor gain
    focus: int | Literal["auto"] | None = None  # lens position 0..255, "auto", unset: fixed

    @field_validator("dist")
    @classmethod
    def _dist_len(cls, v: list[float]) -> list[float]:
        if len(v) not in (0, 4, 5, 8, 12, 14):
            raise ValueError("dist must have 0, 4, 5, 8, 12 or 14 coefficients")
        return v

    @field_validator("focus")
    @classmethod
    def _focus(cls, v: int | str | None) -> int | str | None:
        if isinstance(v, int) and not 0 <= v <= 255:
            raise ValueError(f"focus must be a lens position 0..255 or \"auto\", got {v}")
        return v

    @model_validator(mode="after")
    def _exposure_fits(self) -> CameraConfigBase:
        if self.exposure_us is not None and self.exposure_us > 1e6 / self.fps:
            raise ValueError(f"exposure_us = {self.exposure_us} does not fit in one frame at "
                             f"{self.fps:g} fps (at most {int(1e6 / self.fps)} us): lower it "
                             "or the fps")
        return self

    def model(self) -> CameraModel:
        return CameraModel(self.fx, self.fy, self.cx, self.cy, tuple(self.dist),
                           self.width, self.height)


class SimCameraConfig(CameraConfigBase):
    """The simulated camera: it renders what the simulated arm's camera sees (``[sim]`` holds
    its truth)."""

    kind: Literal["sim"] = "sim"

    @classmethod
    def is_hardware(cls, sim: SimStandIns) -> bool:
        return False


class OakCameraConfig(CameraConfigBase):
    """A Luxonis OAK: which one, and which of its sensors."""

    kind: Literal["oak"] = "oak"
    device_id: str = ""  # serial number (MxId) or IP address; empty: the first device found
    socket: Literal["CAM_A", "CAM_B", "CAM_C", "CAM_D"] = "CAM_B"  # CAM_B: OAK-D's left mono

    @classmethod
    def is_hardware(cls, sim: SimStandIns) -> bool:
        return True


# -- [robot] ------------------------------------------------------------------------------------
class RobotConfigBase(DeviceConfig):
    """What every arm kind takes. ``home_joints_deg`` is where ``cell serve`` starts on a
    simulated arm and what an operator can return to."""

    # The arm's type: its published DH table is the nominal geometry the hand-eye routine's
    # kinematic fit starts from and the reach check solves with (the simulated arm is a UR5e).
    model: Literal["ur3e", "ur5e", "ur10e", "ur16e", "ur20", "ur30"] = "ur5e"
    # Power on and release the brakes when the service starts and after a controller that
    # came back (False: an operator does it from the page or POST /api/v1/arm/power).
    power_on_at_start: bool = False
    # Reconnect tries to a lost arm or camera: first after this, doubling up to the maximum.
    reconnect_initial_s: float = Field(default=0.2, gt=0, le=60)
    reconnect_max_s: float = Field(default=5.0, gt=0, le=300)
    home_joints_deg: tuple[float, float, float, float, float, float] = (
        0.0, -90.0, 90.0, -90.0, -90.0, 0.0)


class UrRobotConfig(RobotConfigBase):
    """A UR controller at ``host`` through ur_rtde (the simulated one with ``[sim]
    ur_controller``, served on that loopback address)."""

    kind: Literal["ur"] = "ur"
    host: str = "127.0.0.1"
    # The UR adapter's timing (URArm): connecting, one call to the controller, the
    # jog watchdog period, and how long unchanged RTDE data may be before the link counts as lost.
    connect_timeout_s: float = Field(default=5.0, gt=0)
    call_timeout_s: float = Field(default=3.0, gt=0)
    watchdog_s: float = Field(default=0.25, gt=0)
    # No new RTDE data for this long = the controller is gone (frozen, cable): generous,
    # because a loaded cell PC can delay the stream reader by most of a second.
    stale_after_s: float = Field(default=1.5, gt=0)

    @classmethod
    def is_hardware(cls, sim: SimStandIns) -> bool:
        return not sim.ur_controller


class SimRobotConfig(RobotConfigBase):
    """The in-process simulated arm (fast tests)."""

    kind: Literal["sim"] = "sim"

    @classmethod
    def is_hardware(cls, sim: SimStandIns) -> bool:
        return False


# -- [gripper] ----------------------------------------------------------------------------------
class RobotiqLink(DeviceConfig):
    """The Modbus RTU link to a Robotiq 2F-85 compatible gripper, and its motion timeouts."""

    slave_id: int = Field(default=9, ge=1, le=247)
    baudrate: Literal[9600, 19200, 38400, 57600, 115200] = 115200  # Robotiq's default: 115200
    timeout_s: float = Field(default=0.5, gt=0)  # one Modbus request
    retries: int = Field(default=1, ge=0, le=10)
    motion_timeout_s: float = Field(default=5.0, gt=0)
    activation_timeout_s: float = Field(default=10.0, gt=0)


class RobotiqGripperConfig(RobotiqLink):
    """A 2F-85 compatible gripper on the serial device ``port`` (needed to build it)."""

    kind: Literal["robotiq"] = "robotiq"
    port: str = ""

    @classmethod
    def is_hardware(cls, sim: SimStandIns) -> bool:
        return True


class SimGripperConfig(RobotiqLink):
    """The simulated gripper, driven through the real Modbus RTU adapter (it closes on the
    simulated world's parts: ``PUT /api/v1/sim/parts``, ``[sim] part_width_mm``). ``link``:
    ``"tcp"``, on the tool flange, its RS-485 relayed as a TCP stream as a UR e-Series
    controller relays it; ``"pty"``, a pseudo-terminal as a USB-RS-485 adapter's device."""

    kind: Literal["sim"] = "sim"
    link: Literal["tcp", "pty"] = "tcp"

    @classmethod
    def is_hardware(cls, sim: SimStandIns) -> bool:
        return False


class NoGripperConfig(DeviceConfig):
    """The cell has no gripper."""

    kind: Literal["none"] = "none"

    @classmethod
    def is_hardware(cls, sim: SimStandIns) -> bool:
        return False


# -- the tables ---------------------------------------------------------------------------------
@dataclass(frozen=True)
class DeviceTable:
    """One device table: its name, the union of its kinds' classes (in the order messages name
    them) and the kind an absent ``kind`` means (None: it is required)."""

    name: str
    union: Any
    default_kind: str | None = None

    @property
    def kinds(self) -> dict[str, type[DeviceConfig]]:
        return {cls.tag(): cls for cls in typing.get_args(self.union)}

    def kind_of(self, raw: Mapping[str, Any]) -> object:
        """The raw table's ``kind``, or the default for one left out."""
        return raw.get("kind", self.default_kind)

    def config_class(self, raw: Mapping[str, Any]) -> type[DeviceConfig] | None:
        """The class the raw table's kind names (None: no valid kind)."""
        kind = self.kind_of(raw)
        return self.kinds.get(kind) if isinstance(kind, str) else None

    def keys(self) -> list[str]:
        """Every key some kind of this table takes (each once, in the kinds' order)."""
        return list(dict.fromkeys(k for c in self.kinds.values() for k in c.model_fields))

    def own_keys(self, raw: Any) -> Any:
        """The raw table as its kind's class reads it: the default kind filled in, and the
        keys only the table's other kinds use left out."""
        if not isinstance(raw, Mapping):
            return raw
        cls = self.config_class(raw)
        out = dict(raw)
        if self.default_kind is not None:
            out.setdefault("kind", self.default_kind)
        if cls is None:
            return out
        others = set(self.keys()) - set(cls.model_fields)
        return {k: v for k, v in out.items() if k not in others}


_Cameras = SimCameraConfig | OakCameraConfig
_Robots = UrRobotConfig | SimRobotConfig
_Grippers = RobotiqGripperConfig | SimGripperConfig | NoGripperConfig

CAMERAS = DeviceTable("camera", _Cameras, default_kind="sim")
ROBOTS = DeviceTable("robot", _Robots)
GRIPPERS = DeviceTable("gripper", _Grippers, default_kind="none")
DEVICE_TABLES = (CAMERAS, ROBOTS, GRIPPERS)

# What ``CellConfig`` holds: the table's class chosen by its ``kind``.
CameraConfig = Annotated[_Cameras, Field(discriminator="kind")]
RobotConfig = Annotated[_Robots, Field(discriminator="kind")]
GripperConfig = Annotated[_Grippers, Field(discriminator="kind")]


def table_of(kind: type[DeviceConfig]) -> DeviceTable | None:
    """The device table that has ``kind`` among its kinds."""
    return next((t for t in DEVICE_TABLES if kind in t.kinds.values()), None)


def with_own_keys(data: Mapping[str, Any]) -> dict[str, Any]:
    """The raw config with each device table as its kind's class reads it
    (:meth:`DeviceTable.own_keys`)."""
    out = dict(data)
    for table in DEVICE_TABLES:
        if table.name in out:
            out[table.name] = table.own_keys(out[table.name])
    return out
