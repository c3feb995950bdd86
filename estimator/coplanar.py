"""Coplanar POSIT (Oberkampf, DeMenthon & Davis 1996) for flat targets.

For a planar model the object matrix only determines I and J up to their components along the
plane normal u: I = I0 + lambda*u, J = J0 + mu*u. The orthogonality and equal-norm constraints
(I.J = 0, |I| = |J|) give (lambda + i*mu)^2 = |J0|^2 - |I0|^2 - 2i I0.J0, i.e. two opposite
solutions -- the two ways a plane can be tilted to produce nearly the same image. Both are kept
as branches from the first iteration on; afterwards each branch keeps, of its own two solutions,
the one that reprojects better (so exactly two branches live, never a growing tree), and the
branch with the lower final error wins. The other branch is returned as the alternative, so the
caller can decide whether the pose is ambiguous. Both branches can drift into the same fixed
point; then there is no distinct alternative and None is returned.

Near-frontal plates are where this iteration is weakest, and not only slow: the true pose is
still a fixed point (exact data reproduce it), but a repelling one. The out-of-plane tilt comes
from the square root above, of a quantity that vanishes for a frontal plate, so near there a
small change of the epsilons changes the tilt a lot. Measured on a plate tilted 8 deg at
620 mm, 14 deg off axis, noise-free: started at the true epsilons plus 1e-6, the deviation
grew 1.33x per step, and the iteration "converged" 30 deg off, with the other branch 8 deg
off. So for such views the seed is only a seed; :func:`estimator.solve.solve_pose` refines it
and searches the second minimum from the mirrored pose, which recovers the exact pose (tested).

Speed: the iteration is scalar arithmetic on a handful of points, so it runs compiled (numba,
cached on disk after the first use): in Python each step cost ~20 us of interpreter and numpy
call overhead for well under a microsecond of arithmetic. The two branches are iterated in
lockstep. Once the winning branch has converged, the other is only followed further while its
error makes it a contender (within ``contender_ratio`` of the winner's); otherwise it is
stopped where it is -- it is reported as the alternative either way, and its pose only has to
be "the other tilt", not a converged one.
"""

from __future__ import annotations

import cmath
import math

import numba
import numpy as np
from numpy.typing import ArrayLike, NDArray

from estimator.arrays import kernel_array
from estimator.camera import CameraModel
from estimator.errors import BehindCameraError, DegenerateGeometryError
from estimator.posit import (
    ObjectModel,
    PositResult,
    reprojection_rms_px,
)

CONTENDER_ERROR_RATIO = 4.0  # a losing branch this much worse than the converged winner stops


@numba.njit(cache=True, nogil=True)
def _candidate(
    I0J0: NDArray[np.float64], sign: float, normal: NDArray[np.float64],
    tail: NDArray[np.float64], xy0: NDArray[np.float64], pts: NDArray[np.float64],
    rows: NDArray[np.float64], eps: NDArray[np.float64],
) -> tuple[float, float, float, float]:
    """One of the two solutions of a coplanar POSIT step -> (scale, error, sx, sy).

    I = I0 + lambda u, J = J0 + mu u with (lambda + i mu)^2 = |J0|^2 - |I0|^2 - 2i I0.J0 (the
    sign picks the solution); writes the rows R1, R2, R3 into ``rows`` (3,3) and the new
    epsilons into ``eps`` (N-1). ``error`` is the summed squared normalised image distance
    (sx + sy, per axis), inf when a point falls behind the camera or I or J vanishes.
    """
    i0x, i0y, i0z, j0x, j0y, j0z = I0J0[0], I0J0[1], I0J0[2], I0J0[3], I0J0[4], I0J0[5]
    ii = i0x * i0x + i0y * i0y + i0z * i0z
    jj = j0x * j0x + j0y * j0y + j0z * j0z
    ij = i0x * j0x + i0y * j0y + i0z * j0z
    root = cmath.sqrt(complex(jj - ii, -2.0 * ij))
    lam, mu = sign * root.real, sign * root.imag
    ux, uy, uz = normal[0], normal[1], normal[2]
    ax, ay, az = i0x + lam * ux, i0y + lam * uy, i0z + lam * uz
    bx, by, bz = j0x + mu * ux, j0y + mu * uy, j0z + mu * uz
    nI = math.sqrt(ax * ax + ay * ay + az * az)
    nJ = math.sqrt(bx * bx + by * by + bz * bz)
    if nI == 0.0 or nJ == 0.0:
        return 1.0, math.inf, math.inf, math.inf
    ax, ay, az = ax / nI, ay / nI, az / nI
    bx, by, bz = bx / nJ, by / nJ, bz / nJ
    cx, cy, cz = ay * bz - az * by, az * bx - ax * bz, ax * by - ay * bx  # R3 = R1 x R2
    rows[0, 0], rows[0, 1], rows[0, 2] = ax, ay, az
    rows[1, 0], rows[1, 1], rows[1, 2] = bx, by, bz
    rows[2, 0], rows[2, 1], rows[2, 2] = cx, cy, cz
    s = math.sqrt(nI * nJ)
    sx = sy = 0.0
    behind = False
    for i in range(tail.shape[0]):
        px, py, pz = tail[i, 0], tail[i, 1], tail[i, 2]
        e = s * (px * cx + py * cy + pz * cz)  # eps_i = P0Pi.R3 / Tz, Tz = 1/s
        eps[i] = e
        depth = 1.0 + e  # depth of Pi over that of P0
        if depth <= 0.0:
            behind = True
            continue
        dx = (s * (px * ax + py * ay + pz * az) + xy0[0]) / depth - pts[i, 0]
        dy = (s * (px * bx + py * by + pz * bz) + xy0[1]) / depth - pts[i, 1]
        sx += dx * dx
        sy += dy * dy
    if behind:
        return s, math.inf, sx, sy
    return s, sx + sy, sx, sy


@numba.njit(cache=True, nogil=True)
def _iterate(
    offset: NDArray[np.float64], gain_t: NDArray[np.float64], normal: NDArray[np.float64],
    tail: NDArray[np.float64], xy0: NDArray[np.float64], pts: NDArray[np.float64],
    radius: NDArray[np.float64], max_iterations: int, tolerance: float,
    contender_ratio: float,
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Both branches in lockstep until converged, stopped or out of iterations.

    Returns ``rows`` (2,3,3) and ``info`` (2,7): per branch [alive, scale, iterations,
    converged, error, sx, sy]; a branch is not alive when its first step already put a point
    behind the camera. A live branch whose both solutions fall behind the camera stops where
    it is; once one branch has converged, the other stops as soon as its error is more than
    ``contender_ratio`` times the winner's.
    """
    m = tail.shape[0]
    rows = np.zeros((2, 3, 3))
    info = np.zeros((2, 7))
    eps = np.zeros((2, m))
    active = np.zeros(2, np.bool_)
    trial_rows = np.zeros((2, 3, 3))
    trial_eps = np.zeros((2, m))
    for b in range(2):  # the first step (all eps zero) gives the two branches
        scale, error, sx, sy = _candidate(offset, 1.0 - 2.0 * b, normal, tail, xy0, pts,
                                          rows[b], eps[b])
        if math.isfinite(error):
            info[b, 0], info[b, 1], info[b, 2] = 1.0, scale, 1.0
            info[b, 4], info[b, 5], info[b, 6] = error, sx, sy
            active[b] = True
    I0J0 = np.empty(6)
    while True:
        live = 0
        for b in range(2):
            if active[b] and info[b, 3] == 0.0:
                live += 1
        if live == 1 and info[0, 0] == 1.0 and info[1, 0] == 1.0:
            done = 0 if info[0, 3] == 1.0 else 1
            other = 1 - done
            if info[done, 3] == 1.0 and info[other, 4] > contender_ratio * info[done, 4] + 1e-18:
                active[other] = False  # a clear loser: not worth iterating to convergence
        stepped = False
        for b in range(2):
            if not active[b] or info[b, 3] == 1.0 or info[b, 2] >= max_iterations:
                continue
            stepped = True
            for k in range(6):
                acc = offset[k]
                for i in range(m):
                    acc += eps[b, i] * gain_t[i, k]
                I0J0[k] = acc
            s0, e0, sx0, sy0 = _candidate(I0J0, 1.0, normal, tail, xy0, pts, trial_rows[0],
                                          trial_eps[0])
            s1, e1, sx1, sy1 = _candidate(I0J0, -1.0, normal, tail, xy0, pts, trial_rows[1],
                                          trial_eps[1])
            k = 0 if e0 <= e1 else 1
            scale, error = (s0, e0) if k == 0 else (s1, e1)
            sx, sy = (sx0, sy0) if k == 0 else (sx1, sy1)
            if not math.isfinite(error):
                active[b] = False  # both of its solutions put a point behind the camera
                continue
            moved = 0.0
            for i in range(m):
                moved = max(moved, abs(trial_eps[k, i] - eps[b, i]) * radius[i])
                eps[b, i] = trial_eps[k, i]
            rows[b] = trial_rows[k]
            info[b, 1], info[b, 4], info[b, 5], info[b, 6] = scale, error, sx, sy
            info[b, 2] += 1.0
            info[b, 3] = 1.0 if moved < tolerance else 0.0
        if not stepped:
            return rows, info


@numba.njit(cache=True, nogil=True)
def _branches(
    object_matrix: NDArray[np.float64], tail: NDArray[np.float64], normal: NDArray[np.float64],
    P0: NDArray[np.float64], xy: NDArray[np.float64], max_iterations: int, tolerance: float,
    contender_ratio: float,
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Both branches from normalised points ``xy`` (N,2) -> (T (2,4,4), info (2,7), as
    :func:`_iterate` reports it).

    The per-frame system (offset, gain, radius: :class:`estimator.posit.FrameSystem`'s, in
    the layout the step reads) is built here and each branch's rows become its pose, P0 at
    depth 1/scale on its image ray: one compiled call per frame instead of a dozen small
    numpy calls, which cost more than the iteration itself.
    """
    m = tail.shape[0]
    x0, y0 = xy[0, 0], xy[0, 1]
    offset = np.zeros(6)
    gain_t = np.empty((m, 6))
    radius = np.empty(m)
    for i in range(m):
        x, y = xy[i + 1, 0], xy[i + 1, 1]
        radius[i] = math.sqrt(x * x + y * y)
        for k in range(3):
            b = object_matrix[k, i]
            offset[k] += b * (x - x0)
            offset[k + 3] += b * (y - y0)
            gain_t[i, k] = b * x
            gain_t[i, k + 3] = b * y
    rows, info = _iterate(offset, gain_t, normal, tail, xy[0], xy[1:], radius, max_iterations,
                          tolerance, contender_ratio)
    T = np.zeros((2, 4, 4))
    for b in range(2):
        if info[b, 0] != 1.0:
            continue
        depth = 1.0 / info[b, 1]
        ray = (x0 * depth, y0 * depth, depth)
        for r in range(3):
            for c in range(3):
                T[b, r, c] = rows[b, r, c]
            T[b, r, 3] = ray[r] - (rows[b, r, 0] * P0[0] + rows[b, r, 1] * P0[1]
                                   + rows[b, r, 2] * P0[2])
        T[b, 3, 3] = 1.0
    return T, info


def _same_rotation(A: NDArray[np.float64], B: NDArray[np.float64]) -> bool:
    """True when two rotations differ by less than ~0.1 deg (branches that merged)."""
    return 0.5 * (float((A[:3, :3] * B[:3, :3]).sum()) - 1.0) > math.cos(2e-3)


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
    Ts, info = _branches(model.object_matrix, model.tail_mm, model.normal, model.origin_mm,
                         kernel_array(xy), max_iterations, tolerance,
                         contender_ratio)
    branches = [b for b in range(2) if info[b, 0] == 1.0]
    if not branches:
        raise BehindCameraError(
            "coplanar POSIT put the target behind the camera in both branches: the image points "
            "probably do not match the model (check the correspondence)"
        )
    scored = []
    fx2, fy2 = camera.fx * camera.fx, camera.fy * camera.fy
    for b in branches:
        error, sx, sy = info[b, 4:].tolist()
        T = Ts[b]
        if camera.has_distortion or not math.isfinite(error):
            rms = reprojection_rms_px(T, model.points_mm, image_points_px, camera)
        else:  # the iteration's own image errors are this pose's (P0's is zero), in pixels
            rms = math.sqrt((sx * fx2 + sy * fy2) / model.n_points)
        scored.append((rms, T, b))
    scored.sort(key=lambda item: item[0])
    rms, T, best = scored[0]
    if not math.isfinite(rms):
        raise DegenerateGeometryError("coplanar POSIT found no pose that reprojects the points")
    alternative = None
    if len(scored) > 1 and not _same_rotation(scored[1][1], T):
        alternative = (scored[1][1], scored[1][0])
    return PositResult(T, int(info[best, 2]), bool(info[best, 3]), rms, alternative)
