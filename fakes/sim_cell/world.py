"""The simulated world: the truth the simulated devices share, and their fault switches.

What the cell may read of it is what its hardware hands it (cell.devices.hardware.SimWorld):
the ``/sim`` routes and the benchmarks score against it; the rest of the cell never sees it.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Generic, TypeVar

import numpy as np
from numpy.typing import NDArray

from fakes.fixed_camera import FixedSimCamera
from fakes.gripper import FakeGripper, LineFault
from fakes.parts import PartPlacement, PartTruth, SimParts
from fakes.sim_camera import SimCamera
from fakes.sim_cell.arm_truth import ArmTruth, ProcessTruth

Matrix4 = NDArray[np.float64]
TruthT = TypeVar("TruthT")


class SimulatedWorld(Generic[TruthT]):
    """Ground truth and fault switches over one simulated arm, camera, gripper and the parts.

    ``truth`` is how its builder describes the world it built (the lens, mount and effects
    resolved from a cell's config); :meth:`truth_values` hands it back unchanged. The target
    (:meth:`true_T_base_target`, :meth:`set_target`) is part 0.
    """

    def __init__(self, arm: ArmTruth, camera: SimCamera, parts: SimParts,
                 gripper: FakeGripper | None, truth: TruthT) -> None:
        self._arm = arm
        self._camera = camera
        self._parts = parts
        self._gripper = gripper
        self._truth = truth

    def truth_values(self) -> TruthT:
        return self._truth

    def true_T_base_target(self, at_s: float | None = None) -> Matrix4:
        """Part 0 at ``at_s`` (a part on a conveyor), or now; a held part where the arm is."""
        return self._parts.first_at(self._parts.now() if at_s is None else at_s,
                                    lambda: self._arm.flange_and_tcp()[0])

    def true_T_base_tcp(self) -> Matrix4:
        return self._arm.flange_and_tcp()[1]

    def true_tcp_sample(self) -> tuple[Matrix4, float]:
        _, T_tcp, t_s = self._arm.flange_and_tcp()
        return T_tcp, t_s

    def set_target(self, T_base_target: Matrix4, velocity_mm_s: NDArray[np.float64] | None = None,
                   angular_velocity_rad_s: NDArray[np.float64] | None = None) -> None:
        self._parts.place_first(T_base_target, velocity_mm_s, angular_velocity_rad_s)

    def place_parts(self, parts: Sequence[PartPlacement]) -> None:
        """Replace the world's parts (ValueError, nothing changed, for one it cannot take)."""
        self._parts.place(parts)

    def parts_truth(self) -> list[PartTruth]:
        """Every part's true pose now, and whether the gripper holds it."""
        T_flange, T_tcp, t_s = self._arm.flange_and_tcp()
        return self._parts.truth(t_s, T_flange, T_tcp)

    def set_tool_board(self, T_flange_board: Matrix4 | None) -> None:
        """Clamp the calibration plate to the tool (None: take it off); fixed cameras only."""
        if not isinstance(self._camera, FixedSimCamera):
            raise RuntimeError("only a simulated fixed camera sees a plate on the tool")
        self._camera.set_tool_board(T_flange_board)

    def set_camera_blocked(self, blocked: bool) -> None:
        self._camera.set_blocked(blocked)

    def trigger_protective_stop(self, reason: str = "test") -> None:
        self._arm.protective_stop(reason)

    def set_camera_lost(self, lost: bool) -> None:
        self._camera.set_lost(lost)

    def kill_controller(self) -> None:
        self._controller().kill_controller()

    def freeze_controller(self, frozen: bool) -> None:
        self._controller().freeze_controller(frozen)

    def start_controller(self) -> None:
        self._controller().start_controller()

    def inject_gripper_fault(self, fault: LineFault, count: int = 1) -> None:
        if self._gripper is None:
            raise RuntimeError("this simulated cell has no simulated gripper")
        self._gripper.inject_line_fault(fault, count)

    def _controller(self) -> ProcessTruth:
        if not isinstance(self._arm, ProcessTruth):
            raise RuntimeError("the in-process simulated arm has no controller to restart")
        return self._arm
