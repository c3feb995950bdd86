"""What a knocked camera changed, from the reference views of a calibration check.

Each view, driven to the joints it was recorded at, sees the reference plate's pose change in
the camera frame by the inverse of the camera's own move on its mount (one rigid change for
every view). The views of a reference pivot about the plate (:func:`plan_poses`), so every view
sees the plate at the same place in its camera frame: a turn of the camera and a shift across
the optical axis move the plate's centre alike in every view, and nothing but the plate's
apparent tilt tells them apart. That tilt is what a pose from one view knows least: once the
plate's image has moved by a pixel or two, each view's tilt is off by up to about a
milliradian (the commissioned lens model and the dot centres are not exact at the new image
place), and carried from the plate to the tool, a few hundred millimetres closer to the camera,
that is tenths of a millimetre. So a turn counts only where the views resolve it: their mean
turn must stand out of its standard error, estimated from the views' own scatter, at the 1 %
level of an F test (``RESOLVED_ALPHA``). An unresolved turn is taken as none, and the change is
the shift that moves the plate's centre as every view sees it move, which the views measure
well; a turn as large as the drift tolerance stands out, and a turn hidden in the noise still
shows at the tool through the plate's shift, rather than a noise-made turn being carried to it.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray
from scipy.spatial.transform import Rotation

from cell.vision.frames import mean_pose
from estimator.transforms import make_T

Matrix4 = NDArray[np.float64]
RESOLVED_ALPHA = 0.01  # the chance that noise alone makes a turn count


def resolved_ratio(n_views: int, alpha: float = RESOLVED_ALPHA) -> float:
    """The squared mean turn over its squared standard error beyond which ``n_views`` views
    resolve a turn: the upper ``alpha`` point of F(2, 2 (n - 1)), the tilt's two poorly known
    axes dominating the scatter (in closed form for two numerator degrees of freedom)."""
    if n_views < 2:
        raise ValueError("a turn's scatter needs at least two views")
    dof = n_views - 1
    return float(dof * (alpha ** (-1.0 / dof) - 1.0))


def turn_resolved(rotvecs_rad: NDArray[np.float64], alpha: float = RESOLVED_ALPHA) -> bool:
    """Whether the views' turns (one rotation vector a row) agree on a turn of their own."""
    n = len(rotvecs_rad)
    mean = rotvecs_rad.mean(axis=0)
    se2 = float(rotvecs_rad.var(axis=0, ddof=1).sum()) / n
    return float(mean @ mean) > resolved_ratio(n, alpha) * se2


def camera_change(changes: list[Matrix4], centres_mm: list[NDArray[np.float64]]) -> Matrix4:
    """The plate's change in the camera frame (``now @ inv(then)``) that explains every view,
    its turn kept only where the views resolve it.

    ``changes``: each view's change of the plate's pose in that view's camera frame;
    ``centres_mm``: the plate's centre (of its dots) in each view's camera frame as recorded.
    """
    rotvecs = Rotation.from_matrix(np.stack([E[:3, :3] for E in changes])).as_rotvec()
    if turn_resolved(rotvecs):
        return mean_pose(changes)
    shifts = [E[:3, :3] @ c + E[:3, 3] - c for E, c in zip(changes, centres_mm, strict=True)]
    return make_T(np.eye(3), np.mean(shifts, axis=0))
