"""Coplanar POSIT (Oberkampf, DeMenthon & Davis 1996) for flat targets.

For a planar model the object matrix only determines I and J up to their components along the
plane normal u: I = I0 + lambda*u, J = J0 + mu*u. The orthogonality and equal-norm constraints
(I.J = 0, |I| = |J|) give (lambda + i*mu)^2 = |J0|^2 - |I0|^2 - 2i I0.J0, i.e. two opposite
solutions -- the two ways a plane can be tilted to produce nearly the same image. Both are kept
as branches from the first iteration on; afterwards each branch keeps, of its own two solutions,
the one that reprojects better (so exactly two branches live, never a growing tree), and the
branch with the lower final error wins. The other branch is returned as the alternative, so the
caller can decide whether the pose is ambiguous. Both branches can drift into the same fixed
point (the iteration is ill-conditioned for plates nearly parallel to the image); then there is
no distinct alternative and None is returned.

Speed: the two branches are iterated in lockstep, so one iteration is one (K,N-1)x(N-1,6)
product for the I0/J0 of every branch, scalar arithmetic for the 2K rotations, and one
(N-1,3)x(3,6K) product that gives every candidate's epsilons and image error at once. Once the
winning branch has converged, the other is only followed further while its error makes it a
contender (within ``CONTENDER_ERROR_RATIO`` of the winner's); otherwise it is stopped where it
is -- it is reported as the alternative either way, and its pose only has to be "the other
tilt", not a converged one.
"""

from __future__ import annotations

import cmath
import math

import numpy as np
from numpy.typing import ArrayLike, NDArray

from estimator.camera import CameraModel
from estimator.errors import BehindCameraError, DegenerateGeometryError
from estimator.posit import (
    FrameSystem,
    ObjectModel,
    PositResult,
    Vec3,
    pose_from_rows,
    reprojection_rms_px,
    unit_rows,
)

CONTENDER_ERROR_RATIO = 4.0  # a losing branch this much worse than the converged winner stops


class _Candidates:
    """Both solutions of one coplanar POSIT step for each of K branches (2K candidates)."""

    def __init__(
        self, model: ObjectModel, system: FrameSystem, eps: NDArray[np.float64] | None
    ) -> None:
        """``eps`` (K, N-1): each branch's epsilons; None for the first step (all zero)."""
        ux, uy, uz = model.normal_tuple
        self.rows: list[tuple[Vec3, Vec3, Vec3] | None] = []
        self.scales: list[float] = []
        cols: list[float] = []  # s*R1, s*R2, s*R3 of every candidate, as the columns of M
        I0J0 = [system.offset.tolist()] if eps is None else (
            eps @ system.gain_t + system.offset).tolist()
        for i0x, i0y, i0z, j0x, j0y, j0z in I0J0:
            ii = i0x * i0x + i0y * i0y + i0z * i0z
            jj = j0x * j0x + j0y * j0y + j0z * j0z
            ij = i0x * j0x + i0y * j0y + i0z * j0z
            root = cmath.sqrt(complex(jj - ii, -2.0 * ij))
            for sign in (1.0, -1.0):
                lam, mu = sign * root.real, sign * root.imag
                solved = unit_rows(
                    (i0x + lam * ux, i0y + lam * uy, i0z + lam * uz),
                    (j0x + mu * ux, j0y + mu * uy, j0z + mu * uz),
                )
                if solved is None:
                    self.rows.append(None)
                    self.scales.append(1.0)
                    cols += (0.0,) * 9
                    continue
                r1, r2, r3, s = solved
                self.rows.append((r1, r2, r3))
                self.scales.append(s)
                cols += (s * r1[0], s * r1[1], s * r1[2], s * r2[0], s * r2[1], s * r2[2],
                         s * r3[0], s * r3[1], s * r3[2])
        k2 = len(cols) // 9
        VR = (model.tail_mm @ np.array(cols).reshape(k2 * 3, 3).T).reshape(-1, k2, 3)
        # VR[i, k] = s*P0Pi.R1, s*P0Pi.R2, eps_i of candidate k; depth of Pi over that of P0:
        depth = 1.0 + VR[:, :, 2:]
        d = (VR[:, :, :2] + system.xy0) / depth - system.pts3
        self.eps = VR[:, :, 2]  # (N-1, 2K)
        # Sum of squared normalised image distances; inf for a point behind the camera.
        squares = (d * d).sum(axis=0)  # (2K, 2): per candidate, x and y separately
        self.squares: list[list[float]] = squares.tolist()
        self.errors: list[float] = [sx + sy for sx, sy in self.squares]
        if depth.min() <= 0.0:
            for k, ok in enumerate((depth.min(axis=0)[:, 0] > 0.0).tolist()):
                if not ok:
                    self.errors[k] = math.inf
        for k, r in enumerate(self.rows):
            if r is None:
                self.errors[k] = math.inf

    def better_of_pair(self, branch: int) -> int:
        """Index of the better (lower error) of branch ``branch``'s two candidates."""
        k = 2 * branch
        return k if self.errors[k] <= self.errors[k + 1] else k + 1


class _Branch:
    """One branch of the iteration: its current candidate and how it got there."""

    def __init__(self, rows: tuple[Vec3, Vec3, Vec3], scale: float, eps: NDArray[np.float64],
                 error: float, squares: list[float]) -> None:
        self.rows, self.scale, self.eps, self.error = rows, scale, eps, error
        self.squares = squares  # summed squared x and y image errors (normalised units)
        self.iterations = 1
        self.converged = False
        self.active = True


def _same_rotation(A: NDArray[np.float64], B: NDArray[np.float64]) -> bool:
    """True when two rotations differ by less than ~0.1 deg (branches that merged)."""
    return 0.5 * (float(np.sum(A[:3, :3] * B[:3, :3])) - 1.0) > math.cos(2e-3)


def _iterate(
    model: ObjectModel, system: FrameSystem, max_iterations: int, tolerance: float,
    contender_ratio: float,
) -> list[_Branch]:
    """Both branches, iterated in lockstep until converged, stopped or out of iterations."""
    first = _Candidates(model, system, None)
    branches = [
        _Branch(first.rows[k], first.scales[k], first.eps[:, k], first.errors[k],  # type: ignore[arg-type]
                first.squares[k])
        for k in range(2) if math.isfinite(first.errors[k])
    ]
    while True:
        live = [b for b in branches if b.active and not b.converged]
        if len(branches) == 2 and len(live) == 1:
            done = branches[0] if branches[1] is live[0] else branches[1]
            if done.converged and live[0].error > contender_ratio * done.error + 1e-18:
                live[0].active = False  # a clear loser: not worth iterating to convergence
                live = []
        live = [b for b in live if b.iterations < max_iterations]
        if not live:
            return branches
        step = _Candidates(model, system, np.array([b.eps for b in live]))
        for j, branch in enumerate(live):
            k = step.better_of_pair(j)
            if not math.isfinite(step.errors[k]):
                branch.active = False  # both of its solutions put a point behind the camera
                continue
            eps = step.eps[:, k]
            moved = float((np.abs(eps - branch.eps) * system.radius).max())
            branch.rows, branch.scale, branch.eps = step.rows[k], step.scales[k], eps  # type: ignore[assignment]
            branch.error, branch.squares = step.errors[k], step.squares[k]
            branch.iterations += 1
            branch.converged = moved < tolerance


def posit_coplanar(
    model: ObjectModel,
    xy: NDArray[np.float64],
    image_points_px: ArrayLike,
    camera: CameraModel,
    max_iterations: int,
    tolerance: float,
    contender_ratio: float = CONTENDER_ERROR_RATIO,
) -> PositResult:
    """Coplanar POSIT on normalised points ``xy``; the better branch wins, the other is kept.

    ``tolerance`` is in normalised units, as in :func:`estimator.posit.posit_general`. Once
    the winning branch has converged, the other stops unless its error is within
    ``contender_ratio`` of the winner's (1.0: stop it as soon as it is behind).
    """
    system = FrameSystem(model, xy)
    branches = _iterate(model, system, max_iterations, tolerance, contender_ratio)
    if not branches:
        raise BehindCameraError(
            "coplanar POSIT put the target behind the camera in both branches: the image points "
            "probably do not match the model (check the correspondence)"
        )
    scored = []
    fx2, fy2 = camera.fx * camera.fx, camera.fy * camera.fy
    for branch in branches:
        T = pose_from_rows(np.array(branch.rows), branch.scale, xy[0], model.points_mm[0],
                           orthonormal=True)
        if camera.has_distortion or not math.isfinite(branch.error):
            rms = reprojection_rms_px(T, model.points_mm, image_points_px, camera)
        else:  # the iteration's own image errors are this pose's (P0's is zero), in pixels
            sx, sy = branch.squares
            rms = math.sqrt((sx * fx2 + sy * fy2) / model.n_points)
        scored.append((rms, T, branch))
    scored.sort(key=lambda item: item[0])
    rms, T, best = scored[0]
    if not math.isfinite(rms):
        raise DegenerateGeometryError("coplanar POSIT found no pose that reprojects the points")
    alternative = None
    if len(scored) > 1 and not _same_rotation(scored[1][1], T):
        alternative = (scored[1][1], scored[1][0])
    return PositResult(T, best.iterations, best.converged, rms, alternative)
