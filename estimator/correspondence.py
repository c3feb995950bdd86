"""Which blob is which dot: hypothesise a matching, predict the other dots, verify with a pose.

Planar targets (the common case) are matched in two steps. The fast one uses the fact that a
front-facing perspective view keeps the convex hull of the dots and its cyclic order, so when
the blobs' hull has as many corners as the model's, only one hypothesis per rotation of the
hull needs testing. If that does not explain every dot (clutter outside the target, a missing
hull dot), the general search tries every quadruple of blobs against a few 4-dot bases of the
model of the same kind (convex, or a triangle around a point), each giving a plane homography
that predicts the remaining dots. Non-planar targets use ordered blob triples and the P3P poses
of a model triangle instead.

Hypotheses are ranked by how many dots they explain, then by how close their homography is to
a rigid view; the best few distinct matchings are then solved with the real pose solver and
judged by reprojection error, so a matching only wins if a rigid pose explains it. If a second,
different matching fits about as well (a symmetric model, or too few dots among clutter), the
result says ``ambiguous`` rather than guessing.
"""

from __future__ import annotations

import math
import statistics
from collections.abc import Callable
from dataclasses import dataclass, replace
from itertools import combinations, permutations

import cv2
import numba
import numpy as np
from numpy.typing import ArrayLike, NDArray

from estimator.ambiguity import MAX_DEG, MAX_DOT_MM
from estimator.arrays import kernel_array
from estimator.camera import CameraModel
from estimator.errors import CorrespondenceError, EstimationError, TooFewBlobsError
from estimator.refine import camera_arrays, covariance_from, pose_reprojection
from estimator.result import AlternativePose, PoseResult
from estimator.solve import solve_pose
from estimator.target import Target

PoseSolver = Callable[[NDArray[np.float64], NDArray[np.float64]], PoseResult]

_MAX_VERIFIED = 8  # distinct matchings checked with the full pose solver
_ACCEPT_RMS_PX = 2.0  # a right matching reprojects far better than this on a calibrated camera
_QUICK_MARGIN_FACTOR = 3.0  # quick scores above factor * best + margin are not solved
_QUICK_MARGIN_PX = 2.0
_MAX_BASIS_DOTS = 12  # model dots the bases are chosen from (bounded set-up for big grids)
_MAX_SEARCH_BLOBS = 12  # blobs the general planar search forms quadruples from


@dataclass(frozen=True)
class Correspondence:
    """The chosen matching: blob ``blob_indices[k]`` is model dot ``model_ids[k]``."""

    model_ids: tuple[int, ...]
    blob_indices: tuple[int, ...]
    pose: PoseResult
    ambiguous: bool
    n_equivalent: int  # matchings (including this one) that fit as well


@dataclass(frozen=True)
class _Model:
    """Per-target data computed once: plane coordinates, hull order, hypothesis bases."""

    planar: bool
    plane_xy: NDArray[np.float64]  # (N,2) in-plane coordinates, front-facing orientation
    plane_h: NDArray[np.float64]  # (3,N) the same, homogeneous, as columns
    hull: tuple[int, ...]  # model indices of the convex hull, counter-clockwise
    bases: tuple[tuple[int, ...], ...]  # 4 (planar) or 3 dots; each dot misses from one
    # Rigid symmetries of the layout other than the identity: (perm, S) with S p_m = p_perm[m]
    # (4x4, target frame); for planar targets only those keeping the plate's front side.
    symmetries: tuple[tuple[tuple[int, ...], NDArray[np.float64]], ...] = ()
    min_symmetry_deg: float = 180.0  # smallest rotation angle among the symmetries


def _ccw_hull(points: NDArray[np.float64], straight_tol: float = 0.0) -> tuple[int, ...]:
    """Indices of the convex hull corners in counter-clockwise order (x right, y down frame).

    Corners within ``straight_tol`` of the line through their neighbours are dropped (most
    straight first): the dots along a grid's edge are no corners, whether noise puts them a
    hair inside or outside the line.
    """
    idx = cv2.convexHull(points.astype(np.float32), clockwise=False, returnPoints=False)
    hull = [int(i) for i in np.asarray(idx).ravel()]
    if straight_tol <= 0.0:
        return tuple(hull)
    xy = points[hull].tolist()
    while len(hull) > 3:
        dist = []
        for k in range(len(hull)):
            (ax, ay), (bx, by), (cx, cy) = xy[k - 1], xy[k], xy[(k + 1) % len(hull)]
            chord = math.hypot(cx - ax, cy - ay)
            dist.append(abs((cx - ax) * (by - ay) - (cy - ay) * (bx - ax)) / max(chord, 1e-12))
        k = min(range(len(hull)), key=dist.__getitem__)
        if dist[k] > straight_tol:
            break
        del hull[k]
        del xy[k]
    return tuple(hull)


def _spread_subset(points: NDArray[np.float64], first: list[int], limit: int) -> list[int]:
    """Up to ``limit`` indices: ``first`` (e.g. hull corners), then farthest-point sampling,
    so a bounded search still spans the whole layout."""
    chosen = list(dict.fromkeys(first))[:limit]
    if not chosen:
        chosen = [int(np.argmax(points[:, 0]))]
    d = np.min(np.linalg.norm(points[:, None] - points[chosen][None], axis=2), axis=1)
    while len(chosen) < min(limit, len(points)):
        k = int(d.argmax())
        if d[k] <= 0.0:
            break
        chosen.append(k)
        d = np.minimum(d, np.linalg.norm(points - points[k], axis=1))
    return chosen


def _plane_coordinates(points_mm: NDArray[np.float64]) -> NDArray[np.float64]:
    """2-D coordinates in the target plane, oriented so a front view keeps the handedness."""
    centred = points_mm - points_mm.mean(axis=0)
    _, _, vt = np.linalg.svd(centred)
    e1, e2 = vt[0], vt[1]
    if np.cross(e1, e2)[2] < 0:  # normal must point along +z (into the plate, away from camera)
        e2 = -e2
    return np.column_stack((centred @ e1, centred @ e2))


def _quad_quality(pts: NDArray[np.float64]) -> float:
    """Smallest triangle area of a 4-point set: small means near-degenerate for a homography."""
    areas = []
    for a, b, c in combinations(range(len(pts)), 3):
        u, v = pts[b] - pts[a], pts[c] - pts[a]
        areas.append(abs(u[0] * v[1] - u[1] * v[0]) / 2.0)
    return float(min(areas))


def _triangle_quality(pts: NDArray[np.float64]) -> float:
    """Area of a 3-D triangle: a large triangle gives a well-conditioned P3P."""
    return float(np.linalg.norm(np.cross(pts[1] - pts[0], pts[2] - pts[0])) / 2.0)


def _choose_bases(points: NDArray[np.float64], planar: bool) -> tuple[tuple[int, ...], ...]:
    """Well-conditioned bases (4 dots for a homography, 3 for P3P) such that every dot is
    absent from at least one of them, so one missing dot cannot defeat the search. Large
    layouts are searched on a spread subset of at most _MAX_BASIS_DOTS dots (hull corners
    first); degenerate bases (three dots on a line, for a homography) are never chosen."""
    pts2 = points if points.shape[1] == 2 else points[:, :2]
    first = list(_ccw_hull(pts2)) if planar else []
    subset = _spread_subset(points, first, _MAX_BASIS_DOTS)
    extent = float(np.ptp(points, axis=0).max())
    scored = []
    for quad in combinations(subset, 4 if planar else 3):
        q = _quad_quality(points[list(quad)]) if planar else _triangle_quality(points[list(quad)])
        if q > 1e-3 * extent * extent:
            scored.append((q, quad))
    scored.sort(reverse=True)
    if not scored:
        return ()
    chosen = [scored[0][1]]
    for dot in subset:
        if all(dot in b for b in chosen):
            for _q, quad in scored:
                if dot not in quad:
                    chosen.append(quad)
                    break
    return tuple(chosen)


def _rigid_fit(src: NDArray[np.float64], dst: NDArray[np.float64]) -> NDArray[np.float64]:
    """The rotation + translation (4x4) taking src onto dst best (Kabsch)."""
    cs, cd = src.mean(axis=0), dst.mean(axis=0)
    U, _, Vt = np.linalg.svd((src - cs).T @ (dst - cd))
    D = np.diag([1.0, 1.0, float(np.sign(np.linalg.det(Vt.T @ U.T)) or 1.0)])
    R = Vt.T @ D @ U.T
    S = np.eye(4)
    S[:3, :3], S[:3, 3] = R, cd - R @ cs
    return S


def _symmetries(
    points_mm: NDArray[np.float64], xy: NDArray[np.float64]
) -> tuple[tuple[tuple[int, ...], NDArray[np.float64]], ...]:
    """In-plane rotations about the centroid that map the planar layout onto itself (the
    only rigid symmetries a front view can show), as (perm, S)."""
    extent = float(np.ptp(xy, axis=0).max())
    tol = 1e-3 * extent
    centred = xy - xy.mean(axis=0)
    radius = np.hypot(centred[:, 0], centred[:, 1])
    ref = int(radius.argmax())
    out = []
    for j in np.flatnonzero(np.abs(radius - radius[ref]) < tol).tolist():
        if j == ref:
            continue
        a = math.atan2(centred[j, 1], centred[j, 0]) - math.atan2(centred[ref, 1],
                                                                  centred[ref, 0])
        c, s_ = math.cos(a), math.sin(a)
        rotated = centred @ np.array([[c, s_], [-s_, c]])
        d = np.linalg.norm(rotated[:, None] - centred[None], axis=2)
        perm = d.argmin(axis=1)
        if d[np.arange(len(xy)), perm].max() > tol or len(set(perm.tolist())) != len(xy):
            continue
        S = _rigid_fit(points_mm, points_mm[perm])
        out.append((tuple(int(k) for k in perm), S))
    return tuple(out)


def _model_for(target: Target) -> _Model:
    planar = target.is_planar
    pts = target.points_mm
    if planar:
        xy = _plane_coordinates(pts)
        plane_h = np.vstack((xy.T, np.ones(len(xy))))
        extent = float(np.ptp(xy, axis=0).max())
        bases = _choose_bases(xy, True)
        if not bases:  # no 4 dots without 3 on a line: P3P on triangles instead
            return _Model(True, xy, plane_h, (), _choose_bases(pts, False),
                          *_symmetry_fields(_symmetries(pts, xy)))
        return _Model(True, xy, plane_h, _ccw_hull(xy, 1e-6 * extent), bases,
                      *_symmetry_fields(_symmetries(pts, xy)))
    return _Model(False, np.zeros((0, 2)), np.zeros((3, 0)), (), _choose_bases(pts, False))


def _symmetry_fields(
    sym: tuple[tuple[tuple[int, ...], NDArray[np.float64]], ...]
) -> tuple[tuple[tuple[tuple[int, ...], NDArray[np.float64]], ...], float]:
    angles = [math.degrees(math.acos(max(-1.0, min(1.0, 0.5 * (np.trace(S[:3, :3]) - 1.0)))))
              for _, S in sym]
    return sym, min(angles, default=180.0)


_MODELS: dict[int, tuple[Target, _Model]] = {}


def _cached_model(target: Target) -> _Model:
    """Model data is computed once per Target object (Targets are immutable)."""
    hit = _MODELS.get(id(target))
    if hit is None or hit[0] is not target:
        hit = (target, _model_for(target))
        _MODELS[id(target)] = hit
    return hit[1]


@numba.njit(cache=True, nogil=True)
def _nearest_blobs(
    preds: NDArray[np.float64], obs: NDArray[np.float64], tol: float
) -> NDArray[np.int64]:
    """(K,N): for each hypothesis and model dot the blob nearest its prediction if within
    ``tol`` and claimed by no other dot of the hypothesis, else -1.

    K x N x M distances of a handful of points each: compiled, because the equivalent numpy
    expression spends its time in a dozen array allocations and reductions per call.
    """
    n_hyp, n_dots, n_obs = preds.shape[0], preds.shape[1], obs.shape[0]
    out = np.full((n_hyp, n_dots), -1, np.int64)
    claims = np.zeros(n_obs, np.int64)
    tol2 = tol * tol
    for k in range(n_hyp):
        claims[:] = 0
        for m in range(n_dots):
            px, py = preds[k, m, 0], preds[k, m, 1]
            best, best_d2 = -1, math.inf
            for b in range(n_obs):
                dx, dy = px - obs[b, 0], py - obs[b, 1]
                d2 = dx * dx + dy * dy
                if d2 < best_d2:
                    best, best_d2 = b, d2
            if best >= 0 and best_d2 < tol2:  # NaN predictions never get here
                out[k, m] = best
                claims[best] += 1
        for m in range(n_dots):
            if out[k, m] >= 0 and claims[out[k, m]] > 1:
                out[k, m] = -1  # a blob claimed by two dots goes to neither
    return out


def _assign(
    preds: NDArray[np.float64], obs: NDArray[np.float64], tol: float, min_count: int
) -> list[dict[int, int]]:
    """For each hypothesis (K,N,2 predictions): model dot -> nearest blob within ``tol``.

    Blobs claimed by two dots go to neither. Hypotheses explaining fewer than ``min_count``
    dots are dropped before any per-hypothesis Python work.
    """
    nearest = _nearest_blobs(kernel_array(preds), kernel_array(obs), float(tol))
    matched = nearest >= 0
    out: list[dict[int, int]] = []
    for k in np.flatnonzero(matched.sum(axis=1) >= min_count).tolist():
        row = nearest[k].tolist()
        out.append({m: b for m, b in enumerate(row) if b >= 0})
    return out


def _homography_predictions(
    model: _Model, src: NDArray[np.float32], dsts: NDArray[np.float32]
) -> NDArray[np.float64]:
    """Model dots mapped through the homography of ``src`` (4,2) to each ``dsts[k]`` (K,4,2):
    (K,N,2)."""
    Hs = np.array([cv2.getPerspectiveTransform(src, dst) for dst in dsts])
    proj = Hs @ model.plane_h  # (K,3,N)
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.asarray((proj[:, :2] / proj[:, 2:]).transpose(0, 2, 1), dtype=float)


def _hull_hypotheses(
    model: _Model, ideal: NDArray[np.float64], tol: float, min_count: int
) -> list[dict[int, int]]:
    """Fast path: match hull corners by rotation only. The blobs' hull is straightened (dots
    along a straight edge are no corners) only when the plain hull has more corners than the
    model's, so a corner a hair off its neighbours' line is kept when the model has it."""
    h = len(model.hull)
    blob_hull = _ccw_hull(ideal)
    if len(blob_hull) > h:
        blob_hull = _ccw_hull(ideal, 0.5 * tol)
    if h < 4 or len(blob_hull) != h:
        return []
    pick = np.array([0, h // 4, h // 2, (3 * h) // 4])
    src = model.plane_xy[[model.hull[i] for i in pick]].astype(np.float32)
    corners = np.asarray(blob_hull)[(pick[None, :] + np.arange(h)[:, None]) % h]  # (h,4)
    dsts = ideal[corners].astype(np.float32)
    return _assign(_homography_predictions(model, src, dsts), ideal, tol, min_count)


def _quad_orders(pts4: NDArray[np.float64], idx: list[int]) -> tuple[int, list[list[int]]]:
    """Orderings of a 4-point set that a front view can map onto each other.

    Convex quadruples: the 4 rotations of the counter-clockwise hull. A triangle with a point
    inside: the 3 rotations of the triangle, inner point last. (A perspective view of a plane
    in front of the camera keeps both the type and the orientation.)
    """
    hull = _ccw_hull(pts4)
    if len(hull) == 4:
        return 4, [[idx[hull[(i + s) % 4]] for i in range(4)] for s in range(4)]
    if len(hull) == 3:
        inner = next(i for i in range(4) if i not in hull)
        return 3, [[idx[hull[(i + s) % 3]] for i in range(3)] + [idx[inner]] for s in range(3)]
    return len(hull), []


def _planar_hypotheses(
    model: _Model, ideal: NDArray[np.float64], tol: float, min_count: int, n_wanted: int
) -> list[dict[int, int]]:
    """General planar search: every blob quadruple against every model basis of its kind."""
    out: list[dict[int, int]] = []
    by_kind: dict[int, list[list[int]]] = {3: [], 4: []}
    pool: list[int] = list(range(len(ideal)))
    if len(ideal) > _MAX_SEARCH_BLOBS:  # bounded: C(12, 4) = 495 quadruples at most
        pool = sorted(_spread_subset(ideal, list(_ccw_hull(ideal, 0.5 * tol)),
                                     _MAX_SEARCH_BLOBS))
    for quad in combinations(pool, 4):
        kind, orders = _quad_orders(ideal[list(quad)], list(quad))
        if orders:
            by_kind[kind] += orders
    for basis in model.bases:
        kind, orders = _quad_orders(model.plane_xy[list(basis)], list(basis))
        if not orders or not by_kind[kind]:
            continue
        src = model.plane_xy[orders[0]].astype(np.float32)
        dsts = ideal[np.array(by_kind[kind])].astype(np.float32)
        preds = _homography_predictions(model, src, dsts)
        out += _assign(preds, ideal, tol, min_count)
        if any(len(h) == n_wanted for h in out):
            break  # every full matching shows up from any basis: the others add nothing
    return out


def _faces_camera(rvec: NDArray[np.float64], tvec: NDArray[np.float64],
                  normal: NDArray[np.float64], centre: NDArray[np.float64]) -> bool:
    """True when the plate's +z normal points away from the camera (its front is seen)."""
    R = cv2.Rodrigues(rvec)[0]
    return float((R @ normal) @ (R @ centre + np.ravel(tvec))) > 0.0


def _general_hypotheses(
    target: Target, model: _Model, ideal: NDArray[np.float64], K: NDArray[np.float64],
    tol: float, min_count: int, n_wanted: int,
) -> list[dict[int, int]]:
    """Ordered blob triples against model triangles, P3P poses each (non-planar targets, and
    planar ones without 4 dots off a common line). A planar target's poses must show its
    front (target +z pointing away from the camera): a mirror-symmetric layout seen from
    behind would otherwise explain the blobs as well, with mirrored labels."""
    out = []
    zero = np.zeros(5)
    normal = None
    if model.planar:
        centred = target.points_mm - target.points_mm.mean(axis=0)
        normal = np.linalg.svd(centred)[2][2]
        normal = normal if normal[2] >= 0 else -normal
        centre = target.points_mm.mean(axis=0)
    pool = list(range(len(ideal)))
    if len(ideal) > _MAX_SEARCH_BLOBS:  # bounded: 12 * 11 * 10 ordered triples at most
        pool = sorted(_spread_subset(ideal, list(_ccw_hull(ideal, 0.5 * tol)),
                                     _MAX_SEARCH_BLOBS))
    for basis in model.bases:
        obj = np.ascontiguousarray(target.points_mm[list(basis)])
        for triple in permutations(pool, 3):
            img = np.ascontiguousarray(ideal[list(triple)])
            n_sol, rvecs, tvecs = cv2.solveP3P(obj, img, K, zero, flags=cv2.SOLVEPNP_P3P)
            keep = [k for k in range(int(n_sol)) if tvecs[k][2, 0] > 0]
            if normal is not None:
                keep = [k for k in keep if _faces_camera(
                    np.asarray(rvecs[k], float), np.asarray(tvecs[k], float), normal, centre)]
            preds = [cv2.projectPoints(target.points_mm, rvecs[k], tvecs[k], K, zero)[0]
                     for k in keep]
            if preds:
                stacked = np.asarray(preds, dtype=float).reshape(len(preds), -1, 2)
                out += _assign(stacked, ideal, tol, min_count)
        if any(len(h) == n_wanted for h in out):
            break  # every full matching shows up from any basis: the others add nothing
    return out


def _permuted(hyp: dict[int, int], perm: tuple[int, ...]) -> dict[int, int]:
    """The matching a layout symmetry makes of ``hyp``: dot m gets the blob of dot perm[m]."""
    return {m: hyp[p] for m, p in enumerate(perm) if p in hyp}


def _rank(
    hypotheses: list[dict[int, int]], min_matched: int, model: _Model | None = None
) -> list[dict[int, int]]:
    """Distinct matchings with the most dots explained, best first. Matchings that a
    symmetry of the layout maps onto each other fit exactly alike: one of each set is kept
    (its equivalents are derived from its pose, not solved)."""
    seen: set[tuple[tuple[int, int], ...]] = set()
    best: list[dict[int, int]] = []
    perms = [] if model is None else [perm for perm, _ in model.symmetries]
    for hyp in hypotheses:
        if len(hyp) < min_matched:
            continue
        key = min([tuple(sorted(hyp.items()))]
                  + [tuple(sorted(_permuted(hyp, perm).items())) for perm in perms])
        if key not in seen:
            seen.add(key)
            best.append(hyp)
    if not best:
        return []
    top = max(len(h) for h in best)
    return [h for h in best if len(h) == top]


def _planar_score(
    model: _Model, hyp: dict[int, int], ideal: NDArray[np.float64], K_inv: NDArray[np.float64]
) -> float:
    """How far a matching is from a rigid view of the plane: the least-squares homography's
    transfer error (px) plus a penalty when its first two columns, with the intrinsics
    removed, are not orthogonal and of equal length, as a rotation's must be."""
    ids = sorted(hyp)
    src = model.plane_xy[ids]
    dst = ideal[[hyp[i] for i in ids]]
    H, _ = cv2.findHomography(src, dst, 0)
    if H is None:
        return float("inf")
    pred = cv2.perspectiveTransform(src.reshape(-1, 1, 2), H).reshape(-1, 2)
    transfer = float(np.sqrt(np.mean(np.sum((pred - dst) ** 2, axis=1))))
    M = K_inv @ H
    n1, n2 = float(np.linalg.norm(M[:, 0])), float(np.linalg.norm(M[:, 1]))
    if n1 <= 0 or n2 <= 0:
        return float("inf")
    rigidity = abs(float(M[:, 0] @ M[:, 1])) / (n1 * n2) + abs(float(np.log(n1 / n2)))
    return transfer + 50.0 * rigidity


def _pnp_score(
    target: Target, hyp: dict[int, int], ideal: NDArray[np.float64], K: NDArray[np.float64]
) -> float:
    """Reprojection rms (px) of a quick SQPnP pose of a matching (non-planar targets)."""
    ids = sorted(hyp)
    obj = target.points_mm[ids]
    img = ideal[[hyp[i] for i in ids]]
    ok, rvec, tvec = cv2.solvePnP(obj, img, K, np.zeros(5), flags=cv2.SOLVEPNP_SQPNP)
    if not ok:
        return float("inf")
    pred, _ = cv2.projectPoints(obj, rvec, tvec, K, np.zeros(5))
    return float(np.sqrt(np.mean(np.sum((pred.reshape(-1, 2) - img) ** 2, axis=1))))


@numba.njit(cache=True, nogil=True)
def _min_spacing_px(points: NDArray[np.float64]) -> float:
    """Smallest distance between two of the points (inf for fewer than two)."""
    best = math.inf
    for i in range(points.shape[0]):
        for j in range(i + 1, points.shape[0]):
            dx, dy = points[i, 0] - points[j, 0], points[i, 1] - points[j, 1]
            best = min(best, dx * dx + dy * dy)
    return math.sqrt(best)


def _default_tolerance(ideal: NDArray[np.float64]) -> float:
    """A quarter of the closest blob spacing, within [1.5, 8] px: a prediction nearer a blob
    than that is unambiguous."""
    return min(max(0.25 * _min_spacing_px(ideal), 1.5), 8.0)


def _drop_outlier(
    matching: dict[int, int], pose: PoseResult, min_matched: int, obs_px: NDArray[np.float64],
    solve: Callable[[NDArray[np.intp], NDArray[np.float64]], PoseResult],
) -> tuple[dict[int, int], PoseResult]:
    """Drop one blob whose residual stands out (a dot merged with clutter or another dot),
    if the rest still determine the pose and fit clearly better without it."""
    res = np.asarray(pose.residuals_px, dtype=float)
    if len(matching) <= min_matched or len(res) != len(matching):
        return matching, pose
    worst = int(res.argmax())
    if res[worst] < max(1.0, 4.0 * statistics.median(res.tolist())):
        return matching, pose
    ids = sorted(matching)
    kept = {i: matching[i] for k, i in enumerate(ids) if k != worst}
    kept_ids = np.array(sorted(kept), dtype=np.intp)
    try:
        pose2 = solve(kept_ids, obs_px[[kept[i] for i in kept_ids]])
    except EstimationError:
        return matching, pose
    if pose2.rms_px < 0.5 * pose.rms_px:
        note = f"dot {ids[worst]} dropped: its blob was {res[worst]:.2f} px off the pose"
        return kept, replace(pose2, notes=(*pose2.notes, note))
    return matching, pose


def _verify(
    ranked: list[dict[int, int]], model: _Model, target: Target,
    ideal: NDArray[np.float64], camera: CameraModel, obs_px: NDArray[np.float64],
    solve: Callable[..., PoseResult],
) -> list[tuple[float, dict[int, int], PoseResult]]:
    """(rms px, matching, pose) of the most plausible distinct matchings, best first.

    With several candidates, a cheap geometric score picks the ones worth solving, and they are
    solved without the perspective-bias step (which moves points by hundredths of a pixel and
    cannot change which matching wins); the winner is re-solved with it by the caller.
    """
    if not ranked:
        return []
    if len(ranked) > 1:
        K_inv = np.asarray(np.linalg.inv(camera.K), dtype=np.float64)
        quick = [
            _planar_score(model, h, ideal, K_inv) if model.planar and model.hull
            else _pnp_score(target, h, ideal, camera.K)
            for h in ranked
        ]
        order = np.argsort(quick, kind="stable")
        # Only contenders get the real solver: a matching whose rigid-view score is far
        # behind the best one's cannot fit about as well once a rigid pose is imposed.
        limit = _QUICK_MARGIN_FACTOR * quick[order[0]] + _QUICK_MARGIN_PX
        ranked = [ranked[i] for i in order if quick[i] <= limit]
    scored: list[tuple[float, dict[int, int], PoseResult]] = []
    for hyp in ranked[:_MAX_VERIFIED]:
        ids = np.array(sorted(hyp), dtype=np.intp)
        blobs = np.array([hyp[i] for i in ids], dtype=np.intp)
        try:
            pose = solve(ids, obs_px[blobs], False) if len(ranked) > 1 else solve(
                ids, obs_px[blobs])
        except EstimationError:
            continue
        scored.append((float(pose.rms_px), hyp, pose))
    scored.sort(key=lambda s: s[0])
    return scored


def match_blobs(
    points_px: ArrayLike,
    target: Target,
    camera: CameraModel,
    *,
    tolerance_px: float | None = None,
    max_missing: int = 1,
    correct_bias: bool = True,
    solver: PoseSolver | None = None,
    prior_T: NDArray[np.float64] | None = None,
    ambiguity: tuple[float, float] = (MAX_DOT_MM, MAX_DEG),
) -> Correspondence:
    """Match detected blob centres (M,2 px) to the target's dots and solve the pose.

    Tolerates extra blobs and up to ``max_missing`` missing dots as long as 4 or more dots
    remain. On a symmetric layout the labellings the symmetry relates fit exactly alike:
    one is solved, the others are reported as ``equivalent_poses``; the kept one is the
    nearest ``prior_T`` (the last known pose, for continuity) or the one with the smallest
    rotation. Raises TooFewBlobsError when there are not enough blobs to try, and
    CorrespondenceError when no matching is explained by a rigid pose.
    """
    obs_px = kernel_array(np.asarray(points_px, dtype=float).reshape(-1, 2))
    n = target.n_points
    min_matched = max(4, n - max_missing)
    if len(obs_px) < min_matched:
        raise TooFewBlobsError(len(obs_px), min_matched, f"the target has {n} dots")
    model = _cached_model(target)
    # Matching happens in ideal (undistorted) pixels, where straight lines stay straight.
    ideal = obs_px
    if camera.has_distortion:
        ideal = camera.undistort_points(obs_px) * [camera.fx, camera.fy] + [camera.cx, camera.cy]
    tol = tolerance_px if tolerance_px is not None else _default_tolerance(ideal)

    def solve(ids: NDArray[np.intp], pts: NDArray[np.float64], bias: bool = correct_bias
              ) -> PoseResult:
        if solver is not None:
            return solver(target.points_mm[ids], pts)
        return solve_pose(target.points_mm[ids], pts, camera,
                          dot_diameter_mm=target.dot_diameter_mm, correct_bias=bias,
                          ambiguity_mm=ambiguity[0], ambiguity_deg=ambiguity[1])

    scored: list[tuple[float, dict[int, int], PoseResult]] = []
    homography = model.planar and bool(model.bases) and len(model.bases[0]) == 4
    if homography:
        scored = _verify(
            _rank(_hull_hypotheses(model, ideal, tol, min_matched), min_matched, model),
            model, target, ideal, camera, obs_px, solve)
        if not scored or len(scored[0][1]) < n or scored[0][0] > _ACCEPT_RMS_PX:
            general = _rank(_planar_hypotheses(model, ideal, tol, min_matched, n), min_matched,
                            model)
            scored = _verify(general, model, target, ideal, camera, obs_px, solve)
    else:
        general = _rank(
            _general_hypotheses(target, model, ideal, camera.K, tol, min_matched, n),
            min_matched, model,
        )
        scored = _verify(general, model, target, ideal, camera, obs_px, solve)
    if not scored:
        raise CorrespondenceError(
            f"no assignment of the {len(obs_px)} blob(s) to the {n} target dots is consistent "
            "with the target geometry: check that the configured target matches the plate and "
            "that clutter does not hide dots"
        )
    if scored[0][0] > _ACCEPT_RMS_PX:
        raise CorrespondenceError(
            f"the best matching reprojects with {scored[0][0]:.2f} px rms (limit "
            f"{_ACCEPT_RMS_PX} px): the camera calibration or the target model does not fit "
            "what is seen"
        )
    best_rms, best, pose = scored[0]
    equal_limit = max(2.0 * best_rms, best_rms + 0.5)
    n_equivalent = sum(1 for s in scored if s[0] <= equal_limit)
    if len(scored) > 1 and correct_bias and solver is None:  # ranked without bias correction
        ids = np.array(sorted(best), dtype=np.intp)
        pose = solve(ids, obs_px[[best[i] for i in ids]])
    best, pose = _drop_outlier(best, pose, min_matched, obs_px, solve)
    identity = "ambiguous" if n_equivalent > 1 else "unique"
    equivalents: list[tuple[dict[int, int], NDArray[np.float64]]] = []
    if model.symmetries:
        best, pose, equivalents, by_continuity = _pick_equivalent(
            model, best, pose, prior_T, target, camera)
        if identity == "unique":
            identity = "continuity" if by_continuity else "symmetry"
    ids_sorted = tuple(sorted(best))
    notes = list(pose.notes)
    if n_equivalent > 1:
        notes.append(
            f"correspondence ambiguous: {n_equivalent} different matchings of blobs to dots fit "
            "about as well (too few dots visible among clutter?); keep all dots in view")
    if equivalents:
        notes.append(
            f"symmetric layout: {len(equivalents) + 1} labellings fit exactly alike; "
            + ("the one nearest the previous pose was kept" if identity == "continuity"
               else "the one with the smallest rotation was chosen; tracking keeps it"))
    ambiguous = pose.ambiguous or n_equivalent > 1 or identity == "symmetry"
    rms = float(pose.rms_px)
    pose = replace(
        pose, ambiguous=ambiguous, notes=tuple(notes), identity=identity,
        equivalent_poses=tuple(AlternativePose(T, rms) for _, T in equivalents))
    return Correspondence(
        model_ids=ids_sorted,
        blob_indices=tuple(best[i] for i in ids_sorted),
        pose=pose,
        ambiguous=ambiguous,
        n_equivalent=max(n_equivalent, len(equivalents) + 1),
    )


def _rotation_cos(A: NDArray[np.float64], B: NDArray[np.float64]) -> float:
    """cos of the rotation angle between two poses' rotations."""
    return 0.5 * (float((A[:3, :3] * B[:3, :3]).sum()) - 1.0)


def _pick_equivalent(
    model: _Model, best: dict[int, int], pose: PoseResult, prior_T: NDArray[np.float64] | None,
    target: Target, camera: CameraModel,
) -> tuple[dict[int, int], PoseResult, list[tuple[dict[int, int], NDArray[np.float64]]], bool]:
    """Among the labellings a layout symmetry makes of the best matching (poses T S), the one
    nearest ``prior_T`` (the previous frames' pose) or, without one, the one with the
    smallest rotation -> (matching, its pose, the others, chosen by continuity).

    The chosen labelling's pose needs no solve: T S reprojects every dot exactly where T put
    the dot it stands in for (and the perspective-bias offsets move with the dots), so only
    the residual order and the covariance (over T S's own rotation vector) are redone.
    """
    T = pose.T_camera_target
    options = [(best, T, tuple(range(target.n_points)))] + [
        (_permuted(best, perm), T @ S, perm) for perm, S in model.symmetries]
    reference = prior_T if prior_T is not None else np.eye(4)
    cos = [_rotation_cos(reference, Tk) for _, Tk, _ in options]
    k = int(np.argmax(cos))
    # Continuity decides only when the prior is clearly nearest one labelling: within half
    # the smallest symmetry rotation of it.
    by_continuity = prior_T is not None and cos[k] > math.cos(
        math.radians(0.5 * model.min_symmetry_deg))
    others = [(m, Tk) for i, (m, Tk, _) in enumerate(options) if i != k]
    if k == 0 or pose.image_points_px is None:
        return best, pose, others, by_continuity
    chosen, T_k, perm = options[k]
    position = {m: i for i, m in enumerate(sorted(best))}
    ids = sorted(chosen)
    order = [position[perm[m]] for m in ids]
    img = np.ascontiguousarray(pose.image_points_px[order])
    K, dist = camera_arrays(camera)
    _, residuals, J = pose_reprojection(target.points_mm[ids], img, K, dist, T_k)
    alt = pose.alternative
    S = np.linalg.solve(T, T_k)
    moved = replace(
        pose, T_camera_target=T_k, image_points_px=img,
        residuals_px=np.sqrt((residuals * residuals).sum(axis=1)),
        covariance=covariance_from(residuals, J),
        alternative=None if alt is None else AlternativePose(alt.T_camera_target @ S,
                                                             alt.rms_px))
    return chosen, moved, others, by_continuity
