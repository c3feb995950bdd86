"""A simulated UR e-Series controller that the unmodified ur_rtde client drives.

RTDE (30004), the script port (30003) with ur_rtde's register-mailbox control script, and the
dashboard (29999) around :class:`fakes.ur_sim.MotionEngine`. Start one per loopback address::

    with URController("127.0.0.2") as ctl:
        ...  # rtde_control.RTDEControlInterface("127.0.0.2") works against it
"""

from fakes.ur_controller.faults import Faults
from fakes.ur_controller.server import CONTROLLER_VERSION, URController

__all__ = ["CONTROLLER_VERSION", "Faults", "URController"]
