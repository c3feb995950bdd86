"""One cell's simulated devices and its parts, built together around the truth they share.

The hardware factory (cell.devices.factory) says what to simulate in plain values
(:mod:`~fakes.sim_cell.spec`) and makes one call, :func:`~fakes.sim_cell.build.build_sim_cell`:
the arm (in this process, or the simulated UR controller in its own), the world's parts
(:mod:`fakes.parts`), the camera that renders what that arm's camera really sees of them, the
gripper (on a TCP relay or a pseudo-terminal) that closes on them, and the
:class:`~fakes.sim_cell.world.SimulatedWorld` over them (ground truth and fault switches).
"""

from fakes.sim_cell.build import SimulatedCell, build_sim_cell
from fakes.sim_cell.spec import (
    ArmSpec,
    CameraSpec,
    FixedMount,
    GripperSpec,
    PartsSpec,
    SensorEffects,
    SimCellSpec,
)
from fakes.sim_cell.world import SimulatedWorld

__all__ = ["ArmSpec", "CameraSpec", "FixedMount", "GripperSpec", "PartsSpec", "SensorEffects",
           "SimCellSpec", "SimulatedCell", "SimulatedWorld", "build_sim_cell"]
