"""Eye-to-hand calibration: a fixed camera and a plate held by the tool.

With ``Y = T_base_camera`` (fixed) and ``Z = T_flange_board`` (fixed),
``T_base_flange_i Z = Y T_camera_board_i`` for every view, i.e.
``inv(T_base_flange_i) Y T_camera_board_i = Z`` is constant: exactly the eye-in-hand relation
(:mod:`estimator.calib.handeye`) with the flange poses inverted. So the same closed forms
(Tsai-Lenz, Park-Martin, Horaud-Dornaika) give ``Y`` where they gave ``T_flange_camera``, and
the same joint refinement on every feature's reprojection gives ``Y`` and ``Z`` together.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
from numpy.typing import NDArray

from estimator.transforms import invert_T

Matrix4 = NDArray[np.float64]


def eye_to_hand_poses(T_base_flange: Sequence[Matrix4]) -> list[Matrix4]:
    """The poses to hand the eye-in-hand solvers: ``inv(T_base_flange_i)``; their answer is
    then ``T_base_camera`` and their fixed "board in base" is ``T_flange_board``."""
    return [invert_T(np.asarray(T, dtype=float)) for T in T_base_flange]
