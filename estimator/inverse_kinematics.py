"""Closed-form inverse kinematics of a Universal Robots arm, batched over poses.

One implementation for everyone who needs joints for a pose: the cell's reachability check
(every sampled pose of every move, so it is vectorised over the poses) and the simulated
controller. UR's geometry (shoulder, elbow and wrist-1 axes parallel, the standard DH table of
:mod:`estimator.kinematics` with ``a1 = a4 = a5 = a6 = 0``) has up to eight solutions per
flange pose, one per :class:`Branch`: the sign of each factor of the Jacobian's determinant,
``det J = a2 a3 s3 s5 (a2 c2 + a3 c23 + d5 s234)``:

- shoulder: the wrist centre in front of or behind the axis of joint 1 (``a2 c2 + a3 c23 +
  d5 s234``, the wrist centre's distance from that axis in the arm's plane, mm);
- elbow: the sign of ``sin q3`` (0 when the arm is stretched or folded);
- wrist: the sign of ``sin q5`` (0 when the axes of joints 4 and 6 line up).

A factor at zero is a singularity, and the only way from one branch to another along a
continuous motion is through one. So a linear move keeps the branch it starts on, and
:func:`branch_of` tells which one that is from the arm's joints.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np
from numpy.typing import ArrayLike, NDArray

from estimator.kinematics import DHTable

Vec = NDArray[np.float64]
_TWO_PI = 2.0 * math.pi
_WRIST_ALIGNED = 1e-7  # |sin q5| under this: q4 and q6 turn about one axis, q6 takes the hint


class Branch(NamedTuple):
    """One of the eight solutions: +1 or -1 each (see the module doc)."""

    shoulder: int
    elbow: int
    wrist: int


BRANCHES: tuple[Branch, ...] = tuple(
    Branch(s, e, w) for s in (1, -1) for e in (1, -1) for w in (1, -1))


@dataclass(frozen=True)
class Solutions:
    """The inverse of N poses, each on its own branch (arrays of length N).

    ``q_rad``: the joints, each in (-pi, pi] (NaN where ``exists`` is False);
    ``shoulder_mm``, ``sin_elbow``, ``sin_wrist``: the three singular factors (signed);
    ``reach_excess_mm``: how far the wrist centre lies beyond what the upper arm and forearm
    span, or inside the reach they leave out near the shoulder (<= 0: within reach);
    ``inside_shoulder_mm``: how far the wrist centre lies inside the cylinder of radius d4
    about the base axis that no solution reaches (<= 0: outside it);
    ``wrist_excess``: how far the flange orientation asks for ``|cos q5| > 1`` (<= 0: fine).
    """

    q_rad: Vec
    exists: NDArray[np.bool_]
    shoulder_mm: Vec
    sin_elbow: Vec
    sin_wrist: Vec
    reach_excess_mm: Vec
    inside_shoulder_mm: Vec
    wrist_excess: Vec


class UrInverse:
    """The closed form for one arm's DH table."""

    def __init__(self, table: DHTable) -> None:
        half = math.pi / 2
        alpha = (half, 0.0, 0.0, half, -half, 0.0)
        a = table.a_mm
        if (any(abs(x) > 1e-12 for x in (a[0], a[3], a[4], a[5]))
                or any(abs(x - y) > 1e-12 for x, y in zip(table.alpha_rad, alpha, strict=True))):
            raise ValueError("the closed form needs UR's structure: a1 = a4 = a5 = a6 = 0 and "
                             "alpha = (pi/2, 0, 0, pi/2, -pi/2, 0)")
        self.table = table
        self._d1, _, _, self._d4, self._d5, self._d6 = table.d_mm
        self._a2, self._a3 = a[1], a[2]
        self._offset = np.asarray(table.theta_offset_rad, dtype=float)

    @property
    def reach_mm(self) -> float:
        """The farthest the wrist centre gets from the shoulder joint (the arm stretched)."""
        return abs(self._a2) + abs(self._a3)

    def solve(self, T_base_flange: ArrayLike, branches: ArrayLike,
              q6_hint_rad: ArrayLike = 0.0) -> Solutions:
        """The solution of each pose ``T_base_flange`` (N x 4 x 4, mm) on its branch
        (N x 3 of +-1, or one row for all). Where the wrist is aligned (``sin q5`` = 0)
        only ``q4 + q6`` is determined: ``q6`` is then ``q6_hint_rad`` (one or N values)."""
        T = np.asarray(T_base_flange, dtype=float).reshape(-1, 4, 4)
        n = T.shape[0]
        b = np.broadcast_to(np.asarray(branches, dtype=float).reshape(-1, 3), (n, 3))
        hint = np.broadcast_to(np.asarray(q6_hint_rad, dtype=float).reshape(-1), (n,))
        d1, d4, d5, d6, a2, a3 = self._d1, self._d4, self._d5, self._d6, self._a2, self._a3
        x6, y6, z6, p6 = T[:, :3, 0], T[:, :3, 1], T[:, :3, 2], T[:, :3, 3]
        p5 = p6 - d6 * z6
        r = np.hypot(p5[:, 0], p5[:, 1])
        inside = abs(d4) - r
        phi = np.arcsin(np.clip(d4 / np.maximum(r, 1e-12), -1.0, 1.0))
        psi = np.arctan2(p5[:, 1], p5[:, 0])
        t1 = np.where(b[:, 0] > 0, psi + phi, psi + math.pi - phi)
        c1, s1 = np.cos(t1), np.sin(t1)
        c5 = (p6[:, 0] * s1 - p6[:, 1] * c1 - d4) / d6
        wrist_excess = np.abs(c5) - 1.0
        t5 = b[:, 2] * np.arccos(np.clip(c5, -1.0, 1.0))
        s5 = np.sin(t5)
        aligned = np.abs(s5) < _WRIST_ALIGNED
        s5_safe = np.where(aligned, 1.0, s5)
        t6 = np.where(aligned, hint, np.arctan2(-(y6[:, 0] * s1 - y6[:, 1] * c1) / s5_safe,
                                                (x6[:, 0] * s1 - x6[:, 1] * c1) / s5_safe))
        c6, s6 = np.cos(t6), np.sin(t6)
        # frame 4's x axis (joint 5's plane) in the arm's plane: c234 along x1, s234 along z0
        v = (c5 * c6)[:, None] * x6 - (c5 * s6)[:, None] * y6 - s5[:, None] * z6
        t234 = np.arctan2(v[:, 2], v[:, 0] * c1 + v[:, 1] * s1)
        c234, s234 = np.cos(t234), np.sin(t234)
        # the origin of frame 3 (the wrist-1 joint) in the arm's plane, from the shoulder joint
        px = p5[:, 0] * c1 + p5[:, 1] * s1 - d5 * s234
        py = p5[:, 2] - d1 + d5 * c234
        dist = np.hypot(px, py)
        reach_excess = np.maximum(dist - (abs(a2) + abs(a3)), abs(abs(a2) - abs(a3)) - dist)
        c3 = (px * px + py * py - a2 * a2 - a3 * a3) / (2.0 * a2 * a3)
        t3 = b[:, 1] * np.arccos(np.clip(c3, -1.0, 1.0))
        s3 = np.sin(t3)
        t2 = np.arctan2(py, px) - np.arctan2(a3 * s3, a2 + a3 * np.cos(t3))
        t4 = t234 - t2 - t3
        q = np.stack([t1, t2, t3, t4, t5, t6], axis=1) - self._offset
        q = np.arctan2(np.sin(q), np.cos(q))
        exists = (inside <= 1e-9) & (wrist_excess <= 1e-9) & (np.abs(c3) <= 1.0 + 1e-9)
        q[~exists] = np.nan
        return Solutions(q, exists, px + d5 * s234, s3, s5, reach_excess, inside, wrist_excess)

    def solve_all(self, T_base_flange: ArrayLike, q6_hint_rad: float = 0.0) -> Solutions:
        """All eight branches of one pose, in the order of :data:`BRANCHES`."""
        T = np.broadcast_to(np.asarray(T_base_flange, dtype=float).reshape(4, 4), (8, 4, 4))
        return self.solve(T, np.array(BRANCHES, dtype=float), q6_hint_rad)

    def singular_factors(self, q_rad: ArrayLike) -> tuple[float, float, float]:
        """``(shoulder_mm, sin_elbow, sin_wrist)`` of a joint configuration."""
        t = np.asarray(q_rad, dtype=float).reshape(6) + self._offset
        t2, t23, t234 = t[1], t[1] + t[2], t[1] + t[2] + t[3]
        shoulder = (self._a2 * math.cos(t2) + self._a3 * math.cos(t23)
                    + self._d5 * math.sin(t234))
        return shoulder, math.sin(t[2]), math.sin(t[4])


def branch_of(factors: tuple[float, float, float]) -> Branch:
    """The branch of a configuration with these singular factors (a zero factor counts +1:
    a configuration on a singularity belongs to both sides)."""
    s, e, w = factors
    return Branch(1 if s >= 0 else -1, 1 if e >= 0 else -1, 1 if w >= 0 else -1)


def wrap_near(q_rad: ArrayLike, q_near_rad: ArrayLike) -> Vec:
    """Per joint, the 2*pi-equivalent of ``q_rad`` nearest ``q_near_rad``."""
    q = np.asarray(q_rad, dtype=float)
    near = np.asarray(q_near_rad, dtype=float)
    return q + _TWO_PI * np.round((near - q) / _TWO_PI)


def unwrap_from(q_start_rad: ArrayLike, q_path_rad: ArrayLike) -> Vec:
    """Joint angles along a path (N x 6, each in (-pi, pi]) made continuous from the joints
    ``q_start_rad`` the arm starts at: each step is the shortest turn from the one before."""
    q0 = np.asarray(q_start_rad, dtype=float).reshape(1, 6)
    q = np.asarray(q_path_rad, dtype=float).reshape(-1, 6)
    steps = np.diff(np.concatenate([q0, q]), axis=0)
    steps = (steps + math.pi) % _TWO_PI - math.pi
    return q0 + np.cumsum(steps, axis=0)
