"""A serial arm's geometry as a standard DH table, and its forward kinematics.

``T_i = Rz(theta_i + theta_offset_i) Tz(d_i) Tx(a_i) Rx(alpha_i)``, lengths in mm, the chain
from the base (frame 0) to the flange (frame 6). The tables are Universal Robots' published
nominal values for the e-Series, the UR20 and the UR30: what an uncalibrated controller
computes its TCP with (the inverse: :mod:`estimator.inverse_kinematics`). A real arm's
joints and links sit a little off them (:meth:`DHTable.perturbed`); the kinematic fit in
:mod:`estimator.calib.kinematic` estimates by how much.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

Matrix4 = NDArray[np.float64]


@dataclass(frozen=True)
class DHTable:
    """Standard DH table of a six-joint arm (mm, rad); ``theta_offset_rad`` is added to each
    joint angle (zero in a published table)."""

    d_mm: tuple[float, ...]
    a_mm: tuple[float, ...]
    alpha_rad: tuple[float, ...]
    theta_offset_rad: tuple[float, ...] = (0.0,) * 6

    def perturbed(self, delta_theta_rad: ArrayLike, delta_d_mm: ArrayLike,
                  delta_a_mm: ArrayLike) -> DHTable:
        """This table with small per-joint errors added: one arm's true geometry."""
        def add(a: tuple[float, ...], b: ArrayLike) -> tuple[float, ...]:
            return tuple(float(x) + float(dx) for x, dx in
                         zip(a, np.asarray(b, dtype=float).reshape(6), strict=True))
        return DHTable(add(self.d_mm, delta_d_mm), add(self.a_mm, delta_a_mm), self.alpha_rad,
                       add(self.theta_offset_rad, delta_theta_rad))


def dh_link(theta_rad: float, d_mm: float, a_mm: float, alpha_rad: float) -> Matrix4:
    """One link's transform, ``T_(i-1)_i``."""
    ct, st = math.cos(theta_rad), math.sin(theta_rad)
    ca, sa = math.cos(alpha_rad), math.sin(alpha_rad)
    return np.array([
        [ct, -st * ca, st * sa, a_mm * ct],
        [st, ct * ca, -ct * sa, a_mm * st],
        [0.0, sa, ca, d_mm],
        [0.0, 0.0, 0.0, 1.0],
    ])


def forward(table: DHTable, q_rad: ArrayLike) -> Matrix4:
    """``T_base_flange`` (mm) at the joint angles ``q_rad``."""
    q = np.asarray(q_rad, dtype=float).reshape(6)
    T = np.eye(4)
    for i in range(6):
        T = T @ dh_link(float(q[i]) + table.theta_offset_rad[i], table.d_mm[i],
                        table.a_mm[i], table.alpha_rad[i])
    return T


_HALF_PI = math.pi / 2
_ALPHA = (_HALF_PI, 0.0, 0.0, _HALF_PI, -_HALF_PI, 0.0)

# Universal Robots' published DH parameters of the e-Series and the UR20 / UR30 (m -> mm).
UR_DH: dict[str, DHTable] = {
    "ur3e": DHTable((151.85, 0.0, 0.0, 131.05, 85.35, 92.1),
                    (0.0, -243.55, -213.2, 0.0, 0.0, 0.0), _ALPHA),
    "ur5e": DHTable((162.5, 0.0, 0.0, 133.3, 99.7, 99.6),
                    (0.0, -425.0, -392.2, 0.0, 0.0, 0.0), _ALPHA),
    "ur10e": DHTable((180.7, 0.0, 0.0, 174.15, 119.85, 116.55),
                     (0.0, -612.7, -571.55, 0.0, 0.0, 0.0), _ALPHA),
    "ur16e": DHTable((180.7, 0.0, 0.0, 174.15, 119.85, 116.55),
                     (0.0, -478.4, -360.0, 0.0, 0.0, 0.0), _ALPHA),
    "ur20": DHTable((236.3, 0.0, 0.0, 201.0, 159.3, 154.3),
                    (0.0, -862.0, -728.7, 0.0, 0.0, 0.0), _ALPHA),
    "ur30": DHTable((236.3, 0.0, 0.0, 201.0, 159.3, 154.3),
                    (0.0, -637.0, -503.7, 0.0, 0.0, 0.0), _ALPHA),
}
