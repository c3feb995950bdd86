"""A constant-velocity (alpha-beta) filter on the target's base-frame pose.

Frames arrive at the camera rate with noise; the servo loop runs faster and needs the target
pose *now* and its velocity (the feed-forward that lets the arm follow a conveyor without a
lag). Each measurement, stamped with its frame's mid-exposure time, corrects the prediction:
position and rotation by ``alpha`` of the innovation, velocity and angular velocity by
``beta / dt`` of it. A constant velocity is tracked without a steady-state lag. Rotations are
handled on the manifold: the innovation is ``log(R_meas R_pred^T)``, a base-frame rotation
vector. Pure maths, unit-tested without a camera.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray
from scipy.spatial.transform import Rotation

Matrix4 = NDArray[np.float64]
Vec = NDArray[np.float64]


@dataclass(frozen=True)
class TargetEstimate:
    T_base_target: Matrix4
    velocity_mm_s: Vec
    angular_velocity_rad_s: Vec
    measured_at_s: float  # time of the last measurement (frame mid-exposure)


class ConstantVelocityFilter:
    def __init__(self, alpha: float = 0.6, beta: float = 0.15, max_dt_s: float = 0.5) -> None:
        if not (0 < alpha <= 1 and 0 <= beta < 2 and beta <= alpha):
            raise ValueError("alpha-beta filter needs 0 < alpha <= 1 and 0 <= beta <= alpha")
        self.alpha, self.beta, self.max_dt_s = alpha, beta, max_dt_s
        self._t: float | None = None
        self._p = np.zeros(3)
        self._R = np.eye(3)
        self._v = np.zeros(3)
        self._w = np.zeros(3)
        self.updates = 0

    @property
    def initialised(self) -> bool:
        return self._t is not None

    def reset(self) -> None:
        self._t = None
        self._v, self._w = np.zeros(3), np.zeros(3)
        self.updates = 0

    def update(self, t_s: float, T_meas: Matrix4) -> None:
        """Fold in one measurement taken at ``t_s``. Older-than-the-state ones are ignored."""
        p_m = np.asarray(T_meas[:3, 3], dtype=float)
        R_m = np.asarray(T_meas[:3, :3], dtype=float)
        if self._t is None:
            self._t, self._p, self._R = t_s, p_m.copy(), R_m.copy()
            self.updates = 1
            return
        dt = t_s - self._t
        if dt <= 0:
            return
        if dt > self.max_dt_s:  # too long without a measurement: the velocity is unknown
            self._t, self._p, self._R = t_s, p_m.copy(), R_m.copy()
            self._v, self._w = np.zeros(3), np.zeros(3)
            self.updates += 1
            return
        p_pred = self._p + self._v * dt
        R_pred = Rotation.from_rotvec(self._w * dt).as_matrix() @ self._R
        r_p = p_m - p_pred
        r_r = Rotation.from_matrix(R_m @ R_pred.T).as_rotvec()
        self._p = p_pred + self.alpha * r_p
        self._R = Rotation.from_rotvec(self.alpha * r_r).as_matrix() @ R_pred
        self._v = self._v + (self.beta / dt) * r_p
        self._w = self._w + (self.beta / dt) * r_r
        self._t = t_s
        self.updates += 1

    def innovation(self, t_s: float, T_meas: Matrix4) -> tuple[float, float]:
        """How far a measurement lies from the prediction: (mm, deg). (0, 0) before the
        first measurement. For a validation gate: a pose that jumps is not this target."""
        if self._t is None:
            return 0.0, 0.0
        T = self.predict(t_s).T_base_target
        d_mm = float(np.linalg.norm(np.asarray(T_meas[:3, 3]) - T[:3, 3]))
        r = Rotation.from_matrix(np.asarray(T_meas[:3, :3]) @ T[:3, :3].T).magnitude()
        return d_mm, float(np.degrees(r))

    def predict(self, t_s: float, max_horizon_s: float | None = None) -> TargetEstimate:
        """The pose at ``t_s`` extrapolated at the estimated velocity (RuntimeError before
        the first measurement). Velocity is reported as zero until two measurements.

        With ``max_horizon_s`` the extrapolation stops that long after the last measurement:
        past it the pose is held and its velocity reported as zero, so a pipeline that has
        gone quiet cannot lead a follower ever further along a guessed path."""
        if self._t is None:
            raise RuntimeError("the target filter has no measurement yet")
        dt = t_s - self._t
        v, w = self._v.copy(), self._w.copy()
        if max_horizon_s is not None and dt > max_horizon_s:
            dt = max_horizon_s
            v, w = np.zeros(3), np.zeros(3)
        T = np.eye(4)
        T[:3, :3] = Rotation.from_rotvec(self._w * dt).as_matrix() @ self._R
        T[:3, 3] = self._p + self._v * dt
        return TargetEstimate(T, v, w, self._t)
