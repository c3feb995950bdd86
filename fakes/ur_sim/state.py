"""Types of the simulated UR controller: modes (UR's codes, from :mod:`drivers.ur.modes`) and
status bits as RTDE reports them, limits, the engine's state snapshot, command outcomes and
errors. Shared by the engine, its commands and the protocol servers.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from enum import Enum, IntEnum
from typing import Literal

import numpy as np
from numpy.typing import ArrayLike, NDArray

# UR's published codes, one definition for both sides of the wire
from drivers.ur.modes import RobotMode, SafetyMode
from fakes.ur_sim.kinematics import elbow_position_m

NUM_JOINTS = 6
CYCLE_S = 0.002  # 500 Hz, the e-Series control rate


class SafetyStatusBit(IntEnum):
    """Bit numbers of RTDE ``safety_status_bits``."""

    NORMAL_MODE = 0
    REDUCED_MODE = 1
    PROTECTIVE_STOPPED = 2
    RECOVERY_MODE = 3
    SAFEGUARD_STOPPED = 4
    SYSTEM_EMERGENCY_STOPPED = 5
    ROBOT_EMERGENCY_STOPPED = 6
    EMERGENCY_STOPPED = 7
    VIOLATION = 8
    FAULT = 9
    STOPPED_DUE_TO_SAFETY = 10


class RobotStatusBit(IntEnum):
    """Bit numbers of RTDE ``robot_status_bits``."""

    POWER_ON = 0
    PROGRAM_RUNNING = 1
    TEACH_BUTTON_PRESSED = 2
    POWER_BUTTON_PRESSED = 3


class EngineError(Exception):
    """Base class: the engine refused a command. Nothing moved because of it."""

    code = "sim_error"


class CommandRejectedError(EngineError):
    """The command itself is invalid: wrong shape, non-finite, outside joint limits,
    unreachable, or asking for more than the arm can do."""

    code = "command_rejected"


class UnreachablePoseError(CommandRejectedError):
    """No inverse-kinematics solution (or none inside the joint limits) for a target/path."""

    code = "unreachable"


class NotRunningError(EngineError):
    """Motion needs robot mode RUNNING (powered, brakes released)."""

    code = "not_running"


class ProtectiveStopActiveError(EngineError):
    """The arm is protective-stopped; motion is refused until :meth:`unlock_protective_stop`.

    Also raised by the command that itself trips the stop (e.g. a TCP speed over the limit).
    """

    code = "protective_stop"


class EmergencyStopActiveError(EngineError):
    """The arm is emergency-stopped; release the e-stop and power on again."""

    code = "emergency_stop"


@dataclass(frozen=True)
class SafetyPlane:
    """A safety plane in the base frame: the TCP must stay where ``normal . p >= offset_m``."""

    normal: tuple[float, float, float]
    offset_m: float
    name: str = "safety plane"

    def __post_init__(self) -> None:
        n = np.asarray(self.normal, dtype=float)
        norm = float(np.linalg.norm(n))
        if n.shape != (3,) or not math.isfinite(norm) or norm < 1e-9:
            raise ValueError(f"safety plane normal must be 3 finite numbers, got {self.normal}")
        object.__setattr__(self, "normal", tuple(float(v) / norm for v in n))

    @staticmethod
    def floor(z_m: float) -> SafetyPlane:
        """A horizontal plane the TCP must stay above (a table top)."""
        return SafetyPlane((0.0, 0.0, 1.0), z_m, "floor")

    def excess_m(self, p_m: ArrayLike) -> float:
        """How far (m) a point is on the forbidden side (<= 0: allowed)."""
        return self.offset_m - float(np.dot(self.normal, p_m))


@dataclass(frozen=True)
class SimLimits:
    """Safety configuration of the simulated arm (UR5e-like defaults)."""

    joint_min_rad: float = -6.283185307179586
    joint_max_rad: float = 6.283185307179586
    max_joint_speed_rad_s: float = 3.14159  # 180 deg/s, UR5e joint maximum
    max_joint_accel_rad_s2: float = 40.0
    max_tcp_speed_m_s: float = 1.5  # safety "tool speed" limit
    max_tcp_accel_m_s2: float = 15.0
    # Safety planes the TCP must not cross. A default controller has none (its only "space"
    # limit is the arm's reach); a cell adds planes for tables and walls.
    safety_planes: tuple[SafetyPlane, ...] = ()
    protective_stop_decel_rad_s2: float = 20.0
    unlock_delay_s: float = 5.0  # a real controller refuses unlock for 5 s after the stop
    servo_watchdog_s: float = 0.02  # servo stream gap (beyond the command's time) before braking
    power_on_s: float = 0.3  # POWER_OFF -> POWER_ON -> IDLE
    brake_release_s: float = 0.4  # IDLE -> RUNNING


Pose6 = list[float]
JogFeature = Literal["base", "tool"]
PathKind = Literal["movej", "movej_pose", "movel", "movel_joints"]
# one waypoint of move_path: (kind, target, speed, accel, blend_m); target is q for "movej" and
# "movel_joints" (URScript movel(q): a straight line to fk(q)) and a pose6 for "movel" and
# "movej_pose" (URScript movej(p[...]): a joint move to the pose's IK nearest the path so far)
PathEntry = tuple[PathKind, Sequence[float], float, float, float]
FaultKind = Literal["protective_stop", "emergency_stop"]


@dataclass(frozen=True)
class EngineSnapshot:
    """A consistent state of the arm, taken under the engine lock (RTDE output fields)."""

    timestamp_s: float  # controller uptime (RTDE ``timestamp``)
    host_monotonic_s: float  # time.monotonic() of the sample, for pose histories
    q: tuple[float, ...]  # actual_q (rad)
    qd: tuple[float, ...]  # actual_qd (rad/s)
    target_q: tuple[float, ...]
    target_qd: tuple[float, ...]
    target_qdd: tuple[float, ...]
    tcp_pose: tuple[float, ...]  # actual_TCP_pose, pose6
    tcp_speed: tuple[float, ...]  # actual_TCP_speed [vx, vy, vz (m/s), wx, wy, wz (rad/s)]
    target_tcp_pose: tuple[float, ...]
    target_tcp_speed: tuple[float, ...]
    tcp_offset: tuple[float, ...]  # pose6 of the TCP in the flange frame
    tcp_force: tuple[float, ...]  # always zero: no contact simulation
    joint_temperatures_c: tuple[float, ...]
    actual_current_a: tuple[float, ...]
    joint_modes: tuple[int, ...]  # UR JointMode per joint (253 RUNNING, 236 POWER_OFF, ...)
    robot_mode: RobotMode
    safety_mode: SafetyMode
    safety_status_bits: int
    robot_status_bits: int
    moving: bool
    active_command: str | None  # "movej", "movel", "path", "speedj", "speedl", "jog", ...
    async_progress: int  # -1 when no move runs, else index of the path segment under way
    speed_scaling: float  # actual speed scaling (0 while stopped by safety)
    target_speed_fraction: float  # the speed slider
    seconds_since_protective_stop: float | None  # None when not protective-stopped
    last_stop_reason: str  # why the last safety stop happened, "" if none
    last_command_id: int  # id returned by the latest accepted motion command (0: none yet)

    # computed on demand: most cycles nobody asks, and the kinematics cost CPU at 500 Hz
    @property
    def elbow_position(self) -> tuple[float, ...]:
        """Elbow joint centre in the base frame (m)."""
        return tuple(map(float, elbow_position_m(self.q)))

    @property
    def elbow_velocity(self) -> tuple[float, ...]:
        """Elbow joint centre velocity (m/s)."""
        if not any(self.qd):
            return (0.0, 0.0, 0.0)
        ahead = [q + 1e-3 * qd for q, qd in zip(self.q, self.qd, strict=True)]
        return tuple(map(float, (elbow_position_m(ahead) - elbow_position_m(self.q)) / 1e-3))


class CommandOutcome(Enum):
    """What became of a motion command (see :meth:`MotionEngine.outcome`)."""

    RUNNING = "running"
    SUCCEEDED = "succeeded"  # arrived / stopped as asked
    ABORTED = "aborted"  # ended by a safety stop or power loss
    PREEMPTED = "preempted"  # replaced by a later command or a stop


Vec = NDArray[np.float64]
HOME_Q_RAD = (0.0, -1.571, 1.571, -1.571, -1.571, 0.0)  # tool pointing down, clear of the base


def as_vector(x: ArrayLike, n: int, what: str) -> Vec:
    try:
        v = np.asarray(x, dtype=float).reshape(-1)
    except (TypeError, ValueError) as err:
        raise CommandRejectedError(f"{what} must be {n} numbers") from err
    if v.shape != (n,) or not np.all(np.isfinite(v)):
        raise CommandRejectedError(f"{what} must be {n} finite numbers, got {x!r}")
    return v


def positive_number(x: float, what: str, limit: float | None = None) -> float:
    v = float(x)
    if not (math.isfinite(v) and v > 0):
        raise CommandRejectedError(f"{what} must be a positive number, got {x!r}")
    if limit is not None and v > limit:
        raise CommandRejectedError(f"{what} {v:g} exceeds the arm's maximum {limit:g}")
    return v
