"""The simulated gripper's fingers closing on the world's parts where the arm truly is."""

from __future__ import annotations

from fakes.parts import SimParts
from fakes.sim_cell.arm_truth import ArmTruth


class PartsGrasp:
    """The :class:`fakes.gripper.Grasp` of a simulated cell: closing takes the part whose grasp
    pose is at the arm's true TCP (:meth:`fakes.parts.SimParts.grip`), opening lets it go."""

    def __init__(self, parts: SimParts, arm: ArmTruth) -> None:
        self._parts = parts
        self._arm = arm

    def grip(self, opening_mm: float, closing_to_mm: float) -> float | None:
        T_flange, T_tcp, t_s = self._arm.flange_and_tcp()
        return self._parts.grip(t_s, T_flange, T_tcp, opening_mm, closing_to_mm)

    def release(self) -> None:
        T_flange, _, t_s = self._arm.flange_and_tcp()
        self._parts.release(t_s, T_flange)
