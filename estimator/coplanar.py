"""Coplanar POSIT (Oberkampf, DeMenthon & Davis 1996) for flat targets.

For a planar model the object matrix only determines I and J up to their components along the
plane normal u: I = I0 + lambda*u, J = J0 + mu*u. The orthogonality and equal-norm constraints
(I.J = 0, |I| = |J|) give (lambda + i*mu)^2 = |J0|^2 - |I0|^2 - 2i I0.J0, i.e. two opposite
solutions -- the two ways a plane can be tilted to produce nearly the same image. Both are kept
as branches from the first iteration on; afterwards each branch keeps, of its own two solutions,
the one that reprojects better, and the branch with the lower final error wins. The other
branch is returned as the alternative, so the caller can decide whether the pose is ambiguous.
Both branches can drift into the same fixed point (the iteration is ill-conditioned for plates
nearly parallel to the image); then there is no distinct alternative and None is returned.
"""

from __future__ import annotations

import cmath
import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from estimator.camera import CameraModel
from estimator.errors import BehindCameraError, DegenerateGeometryError
from estimator.posit import (
    FrameSystem,
    ObjectModel,
    PositResult,
    pose_from_rows,
    reprojection_rms_px,
    rotation_rows,
)


@dataclass
class _Candidate:
    """One coplanar solution at one iteration: rotation rows, scale, epsilons, image error."""

    R_rows: NDArray[np.float64]
    scale: float
    eps: NDArray[np.float64]
    error: float  # sum of squared normalised image distances


@dataclass
class _Branch:
    current: _Candidate
    iterations: int = 1
    converged: bool = False


def _candidates(
    model: ObjectModel, system: FrameSystem, eps: NDArray[np.float64]
) -> list[_Candidate]:
    """Both solutions of one coplanar POSIT step; those with a point behind the camera dropped."""
    i0x, i0y, i0z, j0x, j0y, j0z = system.IJ(eps)
    ii = i0x * i0x + i0y * i0y + i0z * i0z
    jj = j0x * j0x + j0y * j0y + j0z * j0z
    ij = i0x * j0x + i0y * j0y + i0z * j0z
    root = cmath.sqrt(complex(jj - ii, -2.0 * ij))
    ux, uy, uz = model.normal_tuple
    rows: list[NDArray[np.float64]] = []
    scale = 1.0
    for sign in (1.0, -1.0):
        lam, mu = sign * root.real, sign * root.imag
        solved = rotation_rows(
            (i0x + lam * ux, i0y + lam * uy, i0z + lam * uz),
            (j0x + mu * ux, j0y + mu * uy, j0z + mu * uz),
        )
        if solved is None:
            return []
        rows.append(solved[0])
        scale = solved[1]  # |I| = |J| is the same for both signs
    # Both candidates at once: columns s*P0Pi.R1, s*P0Pi.R2, eps_i for each.
    VR = (model.vectors_mm[1:] @ np.concatenate(rows).T) * scale
    depth = 1.0 + VR[:, 2::3]  # depth of Pi over the depth of P0
    dx = (system.x0 + VR[:, 0::3]) / depth - system.pts[:, :1]
    dy = (system.y0 + VR[:, 1::3]) / depth - system.pts[:, 1:]
    errors = np.sum(dx * dx + dy * dy, axis=0).tolist()
    in_front = (depth.min(axis=0) > 0.0).tolist()
    return [
        _Candidate(rows[k], scale, VR[:, 3 * k + 2].copy(), errors[k])
        for k in range(2)
        if in_front[k]
    ]


def _same_rotation(A: NDArray[np.float64], B: NDArray[np.float64]) -> bool:
    """True when two rotations differ by less than ~0.1 deg (branches that merged)."""
    return 0.5 * (float(np.sum(A[:3, :3] * B[:3, :3])) - 1.0) > math.cos(2e-3)


def posit_coplanar(
    model: ObjectModel,
    xy: NDArray[np.float64],
    image_points_px: ArrayLike,
    camera: CameraModel,
    max_iterations: int,
    tolerance: float,
) -> PositResult:
    """Coplanar POSIT on normalised points ``xy``; the better branch wins, the other is kept.

    ``tolerance`` is in normalised units, as in :func:`estimator.posit.posit_general`.
    """
    system = FrameSystem(model, xy)
    branches = [_Branch(c) for c in _candidates(model, system, np.zeros(len(xy) - 1))]
    for branch in branches:
        while not branch.converged and branch.iterations < max_iterations:
            options = _candidates(model, system, branch.current.eps)
            if not options:
                break
            best = min(options, key=lambda c: c.error)
            step = float(np.max(np.abs(best.eps - branch.current.eps) * system.radius))
            branch.current = best
            branch.iterations += 1
            branch.converged = step < tolerance
    if not branches:
        raise BehindCameraError(
            "coplanar POSIT put the target behind the camera in both branches: the image points "
            "probably do not match the model (check the correspondence)"
        )
    scored = []
    for branch in branches:
        c = branch.current
        T = pose_from_rows(c.R_rows, c.scale, xy[0], model.points_mm[0])
        scored.append((reprojection_rms_px(T, model.points_mm, image_points_px, camera), T, branch))
    scored.sort(key=lambda item: item[0])
    rms, T, branch = scored[0]
    if not math.isfinite(rms):
        raise DegenerateGeometryError("coplanar POSIT found no pose that reprojects the points")
    alternative = None
    if len(scored) > 1 and not _same_rotation(scored[1][1], T):
        alternative = (scored[1][1], scored[1][0])
    return PositResult(T, branch.iterations, branch.converged, rms, alternative)
