"""The IBVS approach's final settle: the arm still, the view averaged, one straight step.

Why: near the goal the loop's last motion is along the view's weakest direction (a turn about a
point near the target with the matching shift), where a pixel of RMS image change is tens of
millimetres at the TCP and one frame's dot noise is a few tenths of a millimetre. The loop
measures while it moves, its stop test reads a noisy average, and a camera-mount error bends
the path into that direction (its lever times the rotation the loop corrects). With the arm
still, ``frames`` frames of the same pose average the noise down with no motion inside the
window; the Gauss-Newton step ``-L^+ e`` with the interaction matrix at the goal (the desired
features and depths: the view is there already) is then one short straight move. Repeated until
the step is below the tolerance or the step budget is spent.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from cell.servoing.ibvs import Features, feature_error, interaction_of
from estimator.transforms import T_from_pose

Matrix4 = NDArray[np.float64]
Vec = NDArray[np.float64]


def mean_features(views: list[Features]) -> Features:
    """The dots every view has, their points and depths averaged (views of one still pose)."""
    if not views:
        raise ValueError("no views to average")
    common = tuple(i for i in views[0].ids if all(i in v.ids for v in views[1:]))
    subs = [v.subset(common) for v in views]
    return Features(common, np.mean([s.xy for s in subs], axis=0),
                    np.mean([s.depth_mm for s in subs], axis=0), sum(s.frames for s in subs))


def settle_step(current: Features, desired: Features) -> Vec:
    """The camera's displacement ``[dp mm, dtheta rad]`` (camera frame) that cancels the mean
    image error to first order, with the goal's interaction matrix."""
    desired = desired.subset(current.ids)
    return np.asarray(-np.linalg.pinv(interaction_of(current, desired, "desired"))
                      @ feature_error(current, desired), dtype=float)


def step_goal(T_base_tcp: Matrix4, T_tcp_camera: Matrix4, step: Vec) -> Matrix4:
    """The TCP pose that moves the camera by ``step`` (its own frame) through the hand-eye
    transform. A hand-eye error turns the small step by that error's angle, and its lever
    error times the step's rotation moves it by microns: the next settle measures the rest."""
    T_base_camera = T_base_tcp @ T_tcp_camera
    T_new_camera = T_base_camera @ T_from_pose(step[:3], step[3:])
    return np.asarray(T_new_camera @ np.linalg.inv(T_tcp_camera), dtype=float)


def step_size(step: Vec, T_camera_tcp: Matrix4) -> tuple[float, float]:
    """The step at the TCP point (mm) and its angle (deg)."""
    dp = step[:3] + np.cross(step[3:], T_camera_tcp[:3, 3])
    return float(np.linalg.norm(dp)), float(np.degrees(np.linalg.norm(step[3:])))
