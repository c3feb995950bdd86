"""The pose object of every result: ``{"position_mm": [x, y, z], "rotvec_rad": [rx, ry, rz]}``."""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray

from cell.results.base import Result
from estimator.transforms import T_from_pose, pose_from_T

Vec3 = tuple[float, float, float]


class Pose(Result):
    """A rigid transform as :func:`estimator.transforms.pose_dict` writes it: position in mm,
    rotation as the canonical rotation vector in rad."""

    position_mm: Vec3
    rotvec_rad: Vec3

    @classmethod
    def from_T(cls, T: ArrayLike) -> Pose:
        position_mm, rotvec_rad = pose_from_T(T)
        return cls(position_mm=(position_mm[0], position_mm[1], position_mm[2]),
                   rotvec_rad=(rotvec_rad[0], rotvec_rad[1], rotvec_rad[2]))

    def T(self) -> NDArray[np.float64]:
        """The 4x4 homogeneous transform (mm)."""
        return T_from_pose(self.position_mm, self.rotvec_rad)
