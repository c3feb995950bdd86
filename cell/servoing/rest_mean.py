"""A target at rest, seen from one viewpoint: the mean of its poses, and how sure it is.

One frame's pose of a planar target seen from afar turns by hundredths of a degree from frame
to frame about the target (measured 0.015 deg RMS at 456 mm), which the standoff's lever makes
a tenth of a millimetre at the TCP: a loop that follows each frame, however it filters the
velocity, moves the arm by that much with every frame and cannot hold four frames in a row
within 0.05 mm. A target at rest is better known the longer it is watched: its poses are
averaged, and the mean's standard error falls with the square root of their number.

The poses averaged are those seen from nearly one viewpoint: with the camera's mount a little
off the hand-eye calibration, the target's base-frame pose seems to shift as the arm turns
(by the turn times the mount's error), so the mean starts again whenever the arm has moved
more than ``viewpoint_mm`` / ``viewpoint_deg`` from where its first pose was seen, and
whenever a pose lies farther than ``moved_mm`` / ``moved_deg`` from the mean (the target moved).
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray
from scipy.spatial.transform import Rotation

from cell.vision.frames import mean_pose
from estimator.transforms import pose_distance

Matrix4 = NDArray[np.float64]


@dataclass(frozen=True)
class MeanPose:
    T_base_target: Matrix4
    frames: int
    # the mean's standard error at a point ``lever_mm`` from the target: see :meth:`RestMean.at`
    sem_mm: float
    sem_deg: float


class RestMean:
    def __init__(self, max_frames: int, viewpoint_mm: float = 1.0, viewpoint_deg: float = 0.2,
                 moved_mm: float = 1.0, moved_deg: float = 0.2) -> None:
        self.poses: deque[Matrix4] = deque(maxlen=max_frames)
        self.viewpoint = (viewpoint_mm, viewpoint_deg)
        self.moved = (moved_mm, moved_deg)
        self._from: Matrix4 | None = None  # the TCP the first pose was seen from

    def add(self, T_base_target: Matrix4, T_base_tcp: Matrix4) -> None:
        if self._from is not None and self.poses:
            v_mm, v_deg = pose_distance(self._from, T_base_tcp)
            m_mm, m_deg = pose_distance(self.mean(), T_base_target)
            if v_mm > self.viewpoint[0] or v_deg > self.viewpoint[1] \
                    or m_mm > self.moved[0] or m_deg > self.moved[1]:
                self.poses.clear()
        if not self.poses:
            self._from = np.asarray(T_base_tcp, dtype=float)
        self.poses.append(np.asarray(T_base_target, dtype=float))

    def clear(self) -> None:
        self.poses.clear()

    def __len__(self) -> int:
        return len(self.poses)

    def mean(self) -> Matrix4:
        return mean_pose(list(self.poses))

    def at(self, T_target_goal: Matrix4) -> MeanPose:
        """The mean and its standard error at the goal ``T_target_goal`` (target frame):
        each pose's goal against the mean's, their scatter over the square root of their
        number (none below three poses: the mean is as uncertain as one frame)."""
        T_mean = self.mean()
        n = len(self.poses)
        if n < 3:
            return MeanPose(T_mean, n, float("inf"), float("inf"))
        goal = T_mean @ T_target_goal
        d = np.array([(T @ T_target_goal)[:3, 3] - goal[:3, 3] for T in self.poses])
        r = np.array([Rotation.from_matrix(T[:3, :3] @ T_mean[:3, :3].T).as_rotvec()
                      for T in self.poses])
        sem_mm = float(np.sqrt(np.sum(np.var(d, axis=0, ddof=1)) / n))
        sem_deg = float(np.degrees(np.sqrt(np.sum(np.var(r, axis=0, ddof=1)) / n)))
        return MeanPose(T_mean, n, sem_mm, sem_deg)
