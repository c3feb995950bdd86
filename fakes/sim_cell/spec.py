"""What to simulate: the simulated arm, camera and gripper of one cell, in plain values.

The hardware factory fills these in from the cell's config and the simulated world's resolved
truth (cell.devices.sim_truth); nothing here knows the config.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import numpy as np
from numpy.typing import NDArray

from estimator import CameraModel, Target
from fakes.ur_sim.kinematics import UR5E, UR5eKinematics

Matrix4 = NDArray[np.float64]
NO_ERRORS = (0.0,) * 6


@dataclass(frozen=True)
class ArmSpec:
    """The simulated UR5e: in this process, standing at ``home_joints_rad``, or a simulated UR
    controller in its own process serving ``controller_host`` (running from the start or
    not, as a cell PC that boots before its controller). Its true geometry is the nominal DH
    table the controller reports with plus the ``dh_delta_*`` errors (per joint)."""

    home_joints_rad: tuple[float, ...]
    dh_delta_theta_rad: tuple[float, ...] = NO_ERRORS
    dh_delta_d_mm: tuple[float, ...] = NO_ERRORS
    dh_delta_a_mm: tuple[float, ...] = NO_ERRORS
    controller_host: str | None = None
    controller_running_at_start: bool = True

    def true_kinematics(self) -> UR5eKinematics | None:
        """The arm's true geometry where it differs from the nominal table (None: the nominal
        table is the truth)."""
        if not any((*self.dh_delta_theta_rad, *self.dh_delta_d_mm, *self.dh_delta_a_mm)):
            return None
        return UR5eKinematics(UR5E.perturbed(self.dh_delta_theta_rad, self.dh_delta_d_mm,
                                             self.dh_delta_a_mm))


@dataclass(frozen=True)
class SensorEffects:
    """What a real camera adds to the ideal image: a frame's random gain (relative std), the
    latency from mid-exposure to the host (s, + a half-normal jitter), the timestamp's error
    against the true mid-exposure time (s, + a normal jitter), the image smeared along the
    motion, and light flickering at ``flicker_hz`` (relative depth)."""

    gain_jitter: float = 0.03
    latency_s: float = 0.0
    latency_jitter_s: float = 0.0
    timestamp_offset_s: float = 0.0
    timestamp_jitter_s: float = 0.0
    motion_blur: bool = False
    flicker_depth: float = 0.0
    flicker_hz: float = 100.0


@dataclass(frozen=True, eq=False)
class FixedMount:
    """A camera fixed in the cell: the tool it watches (the TCP on the flange, a body of
    ``tool_radius_mm`` that hides what lies behind it) and a calibration plate clamped to
    the tool at ``T_flange_board`` (None: none)."""

    T_flange_tcp: Matrix4
    tool_radius_mm: float
    T_flange_board: Matrix4 | None = None


@dataclass(frozen=True, eq=False)
class CameraSpec:
    """The simulated camera: the lens it renders with and the one it reports (a calibration,
    as an OAK reports its factory's), where it is (``T_mount``: on the flange, or in the base
    frame with ``fixed``) and the sensor; it sees the world's parts."""

    lens: CameraModel
    reported_lens: CameraModel
    T_mount: Matrix4
    fps: float
    noise_std: float
    blur_sigma_px: float
    effects: SensorEffects = SensorEffects()
    fixed: FixedMount | None = None


@dataclass(frozen=True)
class GripperSpec:
    """The simulated gripper: its Modbus slave id and link (:class:`fakes.gripper.FakeGripper`'s
    transport); it closes on the world's parts."""

    slave_id: int
    activation_time_s: float = 0.2
    transport: Literal["pty", "tcp"] = "tcp"


@dataclass(frozen=True, eq=False)
class PartsSpec:
    """The world's parts at the start: one, the cell's target (``layout``) at
    ``T_base_part``; ``width_mm`` is what the fingers close on, for it and for every part
    placed later without a width of its own."""

    layout: Target
    T_base_part: Matrix4
    width_mm: float


@dataclass(frozen=True)
class SimCellSpec:
    """The parts of one cell to simulate (None: that device is real, or absent) and the
    world's parts (None: none; a camera needs them)."""

    arm: ArmSpec | None = None
    camera: CameraSpec | None = None
    gripper: GripperSpec | None = None
    parts: PartsSpec | None = None
