"""The simulated world: the truth the simulated devices share, and their fault switches.

What the cell may read of it is what its hardware hands it (cell.devices.hardware.SimWorld):
the ``/sim`` routes and the benchmarks score against it; the rest of the cell never sees it.
"""

from __future__ import annotations

import contextlib
import threading
from collections.abc import Sequence
from typing import Generic, Protocol, Self, TypeVar

import numpy as np
from numpy.typing import NDArray

from estimator import CameraModel
from fakes.fixed_camera import FixedSimCamera
from fakes.gripper import FakeGripper, LineFault
from fakes.parts import PartPlacement, PartTruth, SimParts
from fakes.sim_camera import SimCamera
from fakes.sim_cell.arm_truth import ArmTruth, ProcessTruth
from fakes.sim_cell.faults import Faults, FaultSet, faulted_lens, faulted_mount

Matrix4 = NDArray[np.float64]


class WorldTruth(Protocol):
    """How a builder describes the world it built: at least the camera's true lens and mount,
    which the world's faults change."""

    def with_optics(self, camera: CameraModel, T_mount: Matrix4) -> Self:
        """The same description with the camera's lens and mount (on the flange, a fixed
        camera's in the base frame) replaced."""
        ...


TruthT = TypeVar("TruthT", bound=WorldTruth)


class SimulatedWorld(Generic[TruthT]):
    """Ground truth and fault switches over one simulated arm, camera, gripper and the parts.

    ``truth`` is how its builder describes the world it built (the lens, mount and effects
    resolved from a cell's config): the commissioned truth. :meth:`truth_values` hands it back
    with the faults of :meth:`set_faults` applied to the lens and mount. The target
    (:meth:`true_T_base_target`, :meth:`set_target`) is part 0.
    """

    def __init__(self, arm: ArmTruth, camera: SimCamera, parts: SimParts,
                 gripper: FakeGripper | None, truth: TruthT) -> None:
        self._arm = arm
        self._camera = camera
        self._parts = parts
        self._gripper = gripper
        self._truth = truth
        self._optics0 = camera.optics()  # the commissioned lens and mount
        self._faults_lock = threading.Lock()  # one change of faults at a time, all or nothing
        self._faults = Faults()

    def truth_values(self) -> TruthT:
        """The commissioned truth, with the lens and mount the camera has now."""
        with self._faults_lock:
            faults = self._faults
        if faults.T_mount_delta is None and not faults.lens_changed:
            return self._truth
        lens, T_mount = self._camera.optics()
        return self._truth.with_optics(lens, T_mount)

    # -- faults at run time --------------------------------------------------------------------
    def set_faults(self, faults: FaultSet) -> None:
        """Make ``faults`` the world's faults, in place of the ones set before (absent ones
        are cleared): every one applied, or (ValueError: no such part to slip, no fixed
        reference to knock, ...) none, the world as it was."""
        wanted = Faults.of(faults)
        lens0, T_mount0 = self._optics0
        lens, T_mount = faulted_lens(lens0, wanted), faulted_mount(T_mount0, wanted)
        if wanted.T_reference_delta is not None and not self._parts.has_fixed_reference():
            raise ValueError("the simulated world holds no fixed reference to knock (place "
                             "one with fixed_reference)")
        with self._faults_lock:
            optics, reference = self._camera.optics(), self._parts.reference_delta()
            try:
                self._parts.set_reference_delta(wanted.T_reference_delta)
                self._parts.clear_slips()
                if wanted.T_slip is not None:
                    self._parts.set_slip(wanted.slip_part, wanted.T_slip)
                self._camera.set_optics(lens, T_mount)
            except ValueError:
                self._camera.set_optics(*optics)
                self._parts.set_reference_delta(reference)
                self._parts.clear_slips()
                self._restore_slip_locked()
                raise
            self._faults = wanted

    def clear_faults(self) -> None:
        """Back to the commissioned truth: the camera's lens and mount, every fixed reference
        and every slipped part where they were."""
        self.set_faults(Faults())

    def faults(self) -> Faults:
        """The faults in effect; a slip no longer counts once its part was picked or placed
        again (it lies where it was put then)."""
        with self._faults_lock:
            faults = self._faults
        if faults.T_slip is not None and faults.slip_part not in self._parts.slips():
            return faults.without_slip()
        return faults

    def _restore_slip_locked(self) -> None:
        old = self._faults
        if old.T_slip is not None:
            # the part may have been picked or placed again since: nothing to restore then
            with contextlib.suppress(ValueError):
                self._parts.set_slip(old.slip_part, old.T_slip)

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
