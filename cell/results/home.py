"""What a finished home job returns: where the arm stands."""

from __future__ import annotations

from cell.results.base import Result
from cell.results.pose import Pose


class HomeResult(Result):
    joints_deg: list[float]
    T_base_tcp: Pose
