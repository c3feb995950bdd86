"""UR5e forward and analytic inverse kinematics from the published DH parameters.

The simulated controller must report joint and TCP values that agree with each other and with
what a real UR5e would report, so both directions come from the same DH table (standard DH:
``T_i = Rz(theta_i) Tz(d_i) Tx(a_i) Rx(alpha_i)``). Transforms are 4x4 in mm like the rest of
the project. The inverse is the estimator's closed form for UR's geometry (the one the cell's
reachability check uses): up to 8 solutions, from which the one nearest a seed is taken, so
continuous motion never jumps between configurations.
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import ArrayLike, NDArray

from estimator.inverse_kinematics import UrInverse
from estimator.kinematics import UR_DH, DHTable, dh_link
from estimator.transforms import invert_T

TWO_PI = 2.0 * math.pi
_EPS = 1e-9


class UnreachableError(ValueError):
    """No joint solution reaches the pose (out of reach, or none inside the joint limits)."""


# The DH table and its link transform are the estimator's (one formula for the arm the
# simulator is and the one a kinematic calibration fits); the UR5e's is the published one.
DH = DHTable
UR5E = UR_DH["ur5e"]
_dh_T = dh_link


class UR5eKinematics:
    """FK/IK of one arm with a configurable TCP (``T_flange_tcp``, mm)."""

    def __init__(
        self, dh: DH = UR5E, joint_min_rad: float = -TWO_PI, joint_max_rad: float = TWO_PI,
    ) -> None:
        self.dh = dh
        self.joint_min_rad = joint_min_rad
        self.joint_max_rad = joint_max_rad
        self.T_flange_tcp: NDArray[np.float64] = np.eye(4)
        self._T_tcp_flange: NDArray[np.float64] = np.eye(4)
        # the last (q, T_base_tcp, J): IK's final check and the safety check ask for the same q
        self._memo: tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]] | None = (
            None)
        self._inverse: UrInverse | None = None  # built on first use: a perturbed table has none

    def set_tcp(self, T_flange_tcp: ArrayLike) -> None:
        T = np.asarray(T_flange_tcp, dtype=float).reshape(4, 4)
        self.T_flange_tcp = T.copy()
        self._T_tcp_flange = invert_T(T)
        self._memo = None

    # -- forward ----------------------------------------------------------------------------
    def link_frames(self, q_rad: ArrayLike) -> list[NDArray[np.float64]]:
        """``T_base_i`` for i = 0..6 (frame 0 is the base, frame 6 the flange)."""
        q = np.asarray(q_rad, dtype=float).reshape(6)
        frames = [np.eye(4)]
        dh = self.dh
        for i in range(6):
            Ti = _dh_T(float(q[i]) + dh.theta_offset_rad[i], dh.d_mm[i], dh.a_mm[i],
                       dh.alpha_rad[i])
            frames.append(frames[-1] @ Ti)
        return frames

    def forward(self, q_rad: ArrayLike) -> NDArray[np.float64]:
        """``T_base_flange`` (mm)."""
        return self.link_frames(q_rad)[-1]

    def forward_tcp(self, q_rad: ArrayLike) -> NDArray[np.float64]:
        """``T_base_tcp`` (mm) with the configured TCP."""
        return self.forward(q_rad) @ self.T_flange_tcp

    def jacobian_tcp(self, q_rad: ArrayLike) -> NDArray[np.float64]:
        """Geometric Jacobian (6x6) of the TCP: ``[v (mm/s); w (rad/s)] = J @ qd`` in base."""
        return self.tcp_and_jacobian(q_rad)[1]

    def tcp_and_jacobian(self, q_rad: ArrayLike) -> tuple[NDArray[np.float64],
                                                          NDArray[np.float64]]:
        """``T_base_tcp`` and its Jacobian from one pass over the links (the engine needs
        both every control cycle)."""
        q = np.asarray(q_rad, dtype=float).reshape(6)
        memo = self._memo
        if memo is not None and np.array_equal(memo[0], q):
            return memo[1], memo[2]
        frames = self.link_frames(q)
        T_tcp = frames[-1] @ self.T_flange_tcp
        Z = np.array([f[:3, 2] for f in frames[:6]])
        D = T_tcp[:3, 3] - np.array([f[:3, 3] for f in frames[:6]])
        J = np.empty((6, 6))
        # row-wise cross products z_i x (p_tcp - o_i), written out: np.cross is slow on
        # small arrays and this runs at 500 Hz
        J[:3] = (Z[:, [1, 2, 0]] * D[:, [2, 0, 1]] - Z[:, [2, 0, 1]] * D[:, [1, 2, 0]]).T
        J[3:] = Z.T
        self._memo = (q.copy(), T_tcp, J)
        return T_tcp, J

    def inverse_tcp_local(self, T_base_tcp: ArrayLike, q_seed: ArrayLike,
                          q_guess: ArrayLike | None = None, tol_mm: float = 1e-6
                          ) -> NDArray[np.float64]:
        """Newton steps from a nearby guess (default: the seed): the cheap IK for continuous
        motion, where each control cycle moves the TCP by well under a millimetre. Falls back
        to the closed form nearest ``q_seed`` when it does not converge (singularity)."""
        T = np.asarray(T_base_tcp, dtype=float).reshape(4, 4)
        q = np.asarray(q_seed if q_guess is None else q_guess, dtype=float).reshape(6).copy()
        for _ in range(4):
            T_now, J = self.tcp_and_jacobian(q)
            dp = T[:3, 3] - T_now[:3, 3]
            R_err = T[:3, :3] @ T_now[:3, :3].T
            # small-angle rotation vector of the residual (exact enough near convergence)
            dw = 0.5 * np.array([R_err[2, 1] - R_err[1, 2], R_err[0, 2] - R_err[2, 0],
                                 R_err[1, 0] - R_err[0, 1]])
            if float(np.max(np.abs(dp))) < tol_mm and float(np.max(np.abs(dw))) < 1e-9:
                if np.all(q >= self.joint_min_rad) and np.all(q <= self.joint_max_rad):
                    return q
                break
            try:
                q = q + np.linalg.solve(J, np.concatenate([dp, dw]))
            except np.linalg.LinAlgError:
                break
        return self.inverse_tcp(T, q_seed)

    # -- inverse ----------------------------------------------------------------------------
    def inverse_all(self, T_base_flange: ArrayLike, q6_hint_rad: float = 0.0
                    ) -> list[NDArray[np.float64]]:
        """Every closed-form solution with angles in (-pi, pi] (up to 8), unverified limits
        (:class:`estimator.inverse_kinematics.UrInverse`, the one the cell checks reach with).

        At the wrist singularity (q5 = 0 or pi) only q4 +- q6 is determined: q6 is then set to
        ``q6_hint_rad`` and q4 takes up the rest.
        """
        if self._inverse is None:
            self._inverse = UrInverse(self.dh)
        sols = self._inverse.solve_all(T_base_flange, q6_hint_rad)
        return [q.copy() for q, ok in zip(sols.q_rad, sols.exists, strict=True) if ok]

    def _wrap_near(self, q: NDArray[np.float64], q_near: NDArray[np.float64]) -> (
            NDArray[np.float64] | None):
        """Per joint, the 2*pi-equivalent angle nearest the seed inside the limits."""
        out = np.empty(6)
        for i in range(6):
            k = np.round((q_near[i] - q[i]) / TWO_PI)
            best = None
            for kk in (k - 1, k, k + 1):
                v = q[i] + kk * TWO_PI
                if self.joint_min_rad - 1e-9 <= v <= self.joint_max_rad + 1e-9 and (
                        best is None or abs(v - q_near[i]) < abs(best - q_near[i])):
                    best = v
            if best is None:
                return None
            out[i] = best
        return out

    def inverse(self, T_base_flange: ArrayLike, q_near: ArrayLike) -> NDArray[np.float64]:
        """The solution nearest ``q_near`` (max joint difference), within the joint limits.

        Raises :class:`UnreachableError` when no solution exists or none is inside the limits.
        """
        T = np.asarray(T_base_flange, dtype=float).reshape(4, 4)
        seed = np.asarray(q_near, dtype=float).reshape(6)
        candidates: list[tuple[float, NDArray[np.float64]]] = []
        for q in self.inverse_all(T, float(seed[5])):
            qw = self._wrap_near(q, seed)
            if qw is not None:
                candidates.append((float(np.max(np.abs(qw - seed))), qw))
        # Verify in order of preference: clamped acos at the reach boundary can yield a
        # near-miss, and forward kinematics is the arbiter.
        for _, qw in sorted(candidates, key=lambda c: c[0]):
            if _pose_error(self.forward(qw), T) <= 1e-6:
                return qw
        raise UnreachableError("no joint solution within the joint limits reaches the pose")

    def inverse_tcp(self, T_base_tcp: ArrayLike, q_near: ArrayLike) -> NDArray[np.float64]:
        """Joints putting the configured TCP at ``T_base_tcp`` (mm), nearest ``q_near``."""
        T = np.asarray(T_base_tcp, dtype=float).reshape(4, 4)
        return self.inverse(T @ self._T_tcp_flange, q_near)


def _pose_error(A: NDArray[np.float64], B: NDArray[np.float64]) -> float:
    """A cheap combined error (mm + rotation-matrix units) for verifying solutions."""
    dp_m = float(np.max(np.abs(A[:3, 3] - B[:3, 3]))) / 1000.0
    return dp_m + float(np.max(np.abs(A[:3, :3] - B[:3, :3])))


_PLAIN = UR5eKinematics()


def elbow_position_m(q_rad: ArrayLike) -> NDArray[np.float64]:
    """Centre of the elbow joint (the origin of DH frame 2) in the base frame, in m."""
    return _PLAIN.link_frames(q_rad)[2][:3, 3] / 1000.0
