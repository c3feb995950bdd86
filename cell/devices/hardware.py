"""What the hardware factory hands to the cell: the devices behind their interfaces.

The cell's business code sees only these interfaces, never which implementation is behind
them. ``sim`` is the one exception by design: on simulated hardware it gives the API its
``/sim`` routes (ground truth, placing the target and the parts) and tests their fault
switches; on real hardware it is None and those routes do not exist.
"""

from __future__ import annotations

import contextlib
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Literal, Protocol

import numpy as np
from numpy.typing import NDArray

from cell.devices.sim_truth import SimTruthValues
from drivers.arm import Arm
from drivers.camera import Camera
from drivers.gripper import Gripper
from estimator import Target

Matrix4 = NDArray[np.float64]
Vector3 = NDArray[np.float64]


@dataclass(frozen=True, eq=False)
class SimPart:
    """A part to place in the simulated world: its dot layout (``layout_name`` as the caller
    named it, None for the cell's ``[target]``), its true pose, an optional drift in the base
    frame from the moment it is placed (a conveyor) and the width the fingers close on (None:
    ``[sim] part_width_mm``). A ``fixed_reference`` is a plate clamped in the cell: it does
    not drift, the fingers never take it, and a knock of the reference moves it."""

    layout_name: str | None
    layout: Target
    T_base_part: Matrix4
    velocity_mm_s: Vector3 | None = None
    angular_velocity_rad_s: Vector3 | None = None
    width_mm: float | None = None
    fixed_reference: bool = False


@dataclass(frozen=True, eq=False)
class SimFaults:
    """Faults of a simulated cell at run time, each a delta on its commissioned truth and
    neutral when absent: the camera knocked (``T_mount_delta``: the true mount becomes
    ``T_mount0 @ T_mount_delta``; a fixed camera's T_base_camera likewise), the lens's focal
    length scaled and its principal point moved (px), every fixed reference knocked (its
    placed pose ``@ T_reference_delta``) and part ``slip_part`` slipped (``@ T_slip``)."""

    T_mount_delta: Matrix4 | None = None
    focal_scale: float = 1.0
    principal_point_delta_px: tuple[float, float] = (0.0, 0.0)
    T_reference_delta: Matrix4 | None = None
    slip_part: int = 0
    T_slip: Matrix4 | None = None


class SimFaultsInEffect(Protocol):
    """The faults a simulated world has now (as :class:`SimFaults`)."""

    @property
    def T_mount_delta(self) -> Matrix4 | None: ...

    @property
    def focal_scale(self) -> float: ...

    @property
    def principal_point_delta_px(self) -> tuple[float, float]: ...

    @property
    def T_reference_delta(self) -> Matrix4 | None: ...

    @property
    def slip_part(self) -> int: ...

    @property
    def T_slip(self) -> Matrix4 | None: ...


class SimPartTruth(Protocol):
    """One simulated part's truth now: ``T_tcp_part`` is where it sits in the closed fingers
    (None unless ``held``)."""

    @property
    def id(self) -> int: ...

    @property
    def layout_name(self) -> str | None: ...

    @property
    def T_base_part(self) -> Matrix4: ...

    @property
    def held(self) -> bool: ...

    @property
    def width_mm(self) -> float: ...

    @property
    def velocity_mm_s(self) -> Vector3: ...

    @property
    def T_tcp_part(self) -> Matrix4 | None: ...

    @property
    def fixed_reference(self) -> bool: ...

    @property
    def T_slip(self) -> Matrix4 | None:
        """The slip it lies with (T_base_part = where it was placed @ T_slip), None: none."""


class SimWorld(Protocol):
    """Ground truth and fault switches of a simulated cell."""

    def true_T_base_target(self, at_s: float | None = None) -> NDArray[np.float64]:
        """The true target pose (part 0's) now, or at monotonic time ``at_s`` (a moving
        target)."""

    def true_T_base_tcp(self) -> NDArray[np.float64]: ...

    def truth_values(self) -> SimTruthValues:
        """The simulated camera's true lens and mount now (apart from the cell's config; with
        the faults of :meth:`set_faults`)."""

    def true_tcp_sample(self) -> tuple[NDArray[np.float64], float]:
        """The true TCP pose and the monotonic time the simulator had it."""

    def set_target(self, T_base_target: NDArray[np.float64],
                   velocity_mm_s: NDArray[np.float64] | None = None,
                   angular_velocity_rad_s: NDArray[np.float64] | None = None) -> None:
        """Place the target (part 0) now; with velocities (base frame) it drifts from now on.
        The other parts stay where they are."""

    def place_parts(self, parts: Sequence[SimPart]) -> None:
        """Replace every part with ``parts`` (ids 0, 1, ... in order; the fingers hold none
        of them); ValueError, with nothing changed, for one the world cannot take."""

    def parts_truth(self) -> Sequence[SimPartTruth]:
        """Every part's true pose now and whether the gripper holds it, by id."""

    def set_faults(self, faults: SimFaults) -> None:
        """Make ``faults`` the world's faults in place of any set before; ValueError, nothing
        changed, for one it cannot take (no such part to slip, no fixed reference, ...)."""

    def clear_faults(self) -> None:
        """Back to the commissioned truth: lens, mount, references and parts."""

    def faults(self) -> SimFaultsInEffect: ...

    def set_tool_board(self, T_flange_board: NDArray[np.float64] | None) -> None:
        """Clamp the calibration plate to the tool (None: take it off); fixed cameras only."""

    def set_camera_blocked(self, blocked: bool) -> None:
        """Cover (True) or uncover the lens: frames come, the target is not in them."""

    def trigger_protective_stop(self, reason: str = "test") -> None: ...

    def set_camera_lost(self, lost: bool) -> None: ...

    def inject_gripper_fault(self, fault: Literal["garbage", "bad_crc", "no_answer"],
                             count: int = 1) -> None:
        """The next ``count`` gripper transactions fail on the serial line."""

    def freeze_controller(self, frozen: bool) -> None:
        """SIGSTOP (True) or SIGCONT (False) the simulated controller process."""

    def kill_controller(self) -> None:
        """SIGKILL the simulated controller process (RuntimeError for an in-process arm)."""

    def start_controller(self) -> None:
        """Start a simulated controller on the configured address (after a kill, or when
        the config said it is not running at start)."""


@dataclass
class Hardware:
    arm: Arm
    camera: Camera
    gripper: Gripper | None
    simulated: bool  # every device is a fake (sample API tokens are allowed)
    sim: SimWorld | None = None
    closers: list[Callable[[], None]] = field(default_factory=list)
    # Blocks until devices the service started itself (a simulated controller, which boots
    # in its own process while the service starts) can be connected to; the first connect
    # calls it. Real devices boot on their own: nothing to wait for.
    wait_ready: Callable[[], None] = field(default=lambda: None)

    def close(self) -> None:
        """Release devices in reverse order of creation; never raises."""
        for close in reversed(self.closers):
            # shutdown must go on whatever one device does
            with contextlib.suppress(Exception):
                close()
        self.closers.clear()
