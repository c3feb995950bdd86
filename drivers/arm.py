"""The arm interface the cell uses. Adapter: drivers.ur (ur_rtde); fake: fakes (simulated UR).

All poses inside the project are 4x4 transforms in mm (``T_base_tcp``); only adapters convert
to a vendor's wire format. The TCP is the one configured with :meth:`Arm.set_tcp`, so that the
controller, its pendant and the cell agree on what "the tool pose" means.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal, Protocol, runtime_checkable

import numpy as np
from numpy.typing import NDArray

JogFrame = Literal["base", "tool"]


@dataclass(frozen=True)
class ArmState:
    """A consistent snapshot of the arm."""

    connected: bool
    robot_mode: str  # "DISCONNECTED", "POWER_OFF", "IDLE", "RUNNING", ... (UR names)
    safety_status: str  # "NORMAL", "PROTECTIVE_STOP", "EMERGENCY_STOP", "FAULT", ...
    moving: bool
    T_base_tcp: NDArray[np.float64]  # 4x4, mm
    joints_rad: NDArray[np.float64]  # (6,)
    timestamp_s: float  # host time.monotonic() when this state was sampled

    @property
    def protective_stop(self) -> bool:
        return self.safety_status == "PROTECTIVE_STOP"

    @property
    def emergency_stop(self) -> bool:
        return "EMERGENCY_STOP" in self.safety_status

    @property
    def ready(self) -> bool:
        """Connected, powered, brakes released and no safety stop: motion may be commanded."""
        return self.connected and self.robot_mode == "RUNNING" and self.safety_status == "NORMAL"


@runtime_checkable
class Arm(Protocol):
    """A 6-axis arm. Motion methods raise ``drivers.errors`` types; they never hang."""

    def connect(self) -> None:
        """Connect; ConnectionLostError when unreachable, NotReadyError when not in remote."""

    def disconnect(self) -> None: ...

    def power_on(self) -> None:
        """Power on and release the brakes; returns when the arm is RUNNING."""

    def power_off(self) -> None:
        """Power the arm off (brakes engage). Refused by the controller while it moves."""

    def set_tcp(self, T_flange_tcp: NDArray[np.float64]) -> None: ...

    def state(self) -> ArmState: ...

    def tcp_pose(self) -> NDArray[np.float64]:
        """Current ``T_base_tcp`` (mm)."""

    def joint_positions_rad(self) -> NDArray[np.float64]: ...

    def forward_kinematics(self, joints_rad: NDArray[np.float64]) -> NDArray[np.float64]:
        """``T_base_tcp`` (mm) the arm would have at ``joints_rad``, with the configured TCP:
        the controller's own kinematics, so a joint move can be checked before it is sent."""

    def pose_at(self, timestamp_s: float) -> NDArray[np.float64]:
        """``T_base_tcp`` at a past ``time.monotonic()`` instant, from the pose history.

        Raises LookupError when the instant is outside the kept history.
        """

    def move_linear(
        self, T_base_tcp: NDArray[np.float64], speed_mm_s: float, accel_mm_s2: float,
        wait: bool = True,
    ) -> None:
        """Straight-line TCP move. With wait=False returns at once; poll :meth:`is_moving`."""

    def move_joint(
        self, joints_rad: NDArray[np.float64], speed_rad_s: float, accel_rad_s2: float,
        wait: bool = True,
    ) -> None: ...

    def wait_for_motion(self, timeout_s: float | None = None) -> None:
        """Return when the last move sent with ``wait=False`` is over, as the controller says
        (reached, stopped or ended by a fault: the caller reads where the arm is). Raises the
        safety stops' errors, and MotionError when it does not end within ``timeout_s``
        (None: a deadline the adapter derives from the move)."""

    def is_moving(self) -> bool: ...

    def jog(
        self, velocity: NDArray[np.float64], frame: JogFrame = "base",
        accel_mm_s2: float = 500.0,
    ) -> None:
        """Cartesian velocity ``[vx, vy, vz (mm/s), wx, wy, wz (rad/s)]`` in base or tool frame.

        Must be re-sent to keep moving: the arm stops on its own when commands stop arriving
        for longer than the adapter's watchdog period.
        """

    def servo_twist(
        self, velocity: NDArray[np.float64], accel_mm_s2: float, watchdog_s: float,
        angular_accel_rad_s2: float | None = None,
    ) -> None:
        """Streamed base-frame TCP twist ``[vx, vy, vz (mm/s), wx, wy, wz (rad/s)]``.

        For closed-loop control: sent every control tick, reached with at least
        ``accel_mm_s2`` and ``angular_accel_rad_s2`` (None: ``accel_mm_s2 / 1000`` rad/s^2,
        UR's rule); an arm with one acceleration for both takes the larger. When no new
        command arrives within ``watchdog_s`` the arm brakes to a stop on its own, so a
        controller that dies cannot leave it moving.
        """

    def stop(self, decel_mm_s2: float = 2000.0) -> None:
        """Stop any motion now. Always accepted, also when nothing moves."""

    def recover_protective_stop(self) -> None:
        """Unlock a protective stop. UnlockTooEarlyError (with ``retry_in_s``) while the
        controller still refuses, as a real UR does for the first 5 s after the stop."""


def speedl_accel(accel_mm_s2: float, angular_accel_rad_s2: float | None) -> float:
    """The one acceleration URScript's speedl gets when only ``a`` is sent (its aRot then
    takes the same number in rad/s^2): ``a`` in m/s^2, large enough for both parts."""
    a = accel_mm_s2 / 1000.0
    return a if angular_accel_rad_s2 is None else max(a, float(angular_accel_rad_s2))
