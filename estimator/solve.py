"""solve_pose: POSIT / coplanar POSIT seeds, LM refinement, optional perspective-bias correction.

POSIT needs no initial guess but is only a seed: at close range it can stop at a wrong fixed
point, and coplanar POSIT's iteration can drift away from the true pose. So the seed is refined
to the maximum-likelihood pose by one LM run; for planar models the mirrored pose (depth
reversed about the line of sight) and the other coplanar branch are candidates for the second
local minimum, scored raw (one projection each) and refined only when their raw rms makes them
contenders, so both minima are found even when both coplanar branches fell into one basin; and
when the best refined pose still reprojects badly (> RETRY_RMS_PX) the seeds are recomputed
with each other point as POSIT's reference point (which changes the fixed-point iteration).
The refined pose with the lowest rms wins. The perspective-bias correction then moves it by
one first-order step to the corrected points' minimum (the correction is hundredths of a
pixel; :func:`estimator.refine.shift_pose`), not a re-run.

Cost per planar solve (6 dots): one compiled call of coplanar POSIT to a 4 px seed (LM
finishes the job faster than more POSIT iterations would), one LM (MINPACK, see
:mod:`estimator.refine`), one more for a contending alternative, and one linear step for the
bias-corrected points. Every candidate is refined to full precision: a minimum only roughly
reached can lie far enough along a flat valley to pass for a distinct one and stop the search
for the real other minimum (seen at close range). Tracking skips POSIT entirely
(:func:`solve_pose_near`).

Ambiguity (planar targets): the best pose B and the best *distinct* other pose A (rotation
differing by more than ~0.06 deg or translation by more than 0.1 % of the range) are both local
minima of the reprojection error. For planar targets ``alternative`` is always filled: the
refined other minimum, or -- when there is no second minimum -- the unrefined losing coplanar
branch (or the mirrored pose). ``ambiguous`` is decided by :func:`estimator.ambiguity.
ambiguity_test`: the alternative must differ at the dots (default 1 mm / 1 deg) and not be
separable at the noise level measured from B's residuals (likelihood-ratio test); the result
carries the test and its margin (``ambiguity``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numba
import numpy as np
from numpy.typing import ArrayLike, NDArray

from estimator.ambiguity import MAX_DEG, MAX_DOT_MM, ambiguity_test
from estimator.arrays import kernel_array
from estimator.bias import centroid_bias_px
from estimator.camera import CameraModel
from estimator.coplanar import posit_coplanar
from estimator.errors import BehindCameraError, EstimationError, NotConvergedError
from estimator.posit import (
    ObjectModel,
    all_in_front,
    normalised_image_points,
    object_model,
    posit_general,
    reprojection_rms_px,
)
from estimator.refine import (
    camera_arrays,
    covariance_from,
    pose_reprojection,
    refine_arrays,
    refine_fit,
    shift_pose,
)
from estimator.result import AlternativePose, Blob, PoseResult

RETRY_RMS_PX = 1.0  # best refined rms above this: try the other reference points too
BAD_RMS_PX = 2.0  # an unconverged seed whose refined rms is above this is a failure
SEED_MAX_ITERATIONS = 100
SEED_TOLERANCE_PX = 0.05  # the seed only has to land in the right basin; LM does the rest
# Coplanar POSIT converges more slowly (error ratio ~0.45 per iteration) and each iteration
# costs more (two branches, four candidates), while LM takes a few-pixel seed in its stride.
# Iterating on to 0.005 px (cheap now that the steps are compiled) would save ~2 LM evaluations
# per frame, but on a close-range 5-dot plate both converged branches and the mirror then led
# only to a wrong minimum (0.44 px rms against 0.005 px at the truth, 7.7 mm off), where the
# 4 px seed still lay in the true basin: tests/estimator/test_solve_pose.py keeps that frame.
PLANAR_SEED_TOLERANCE_PX = 4.0
CONTENDER_RAW_RMS_PX = 8.0  # an unrefined alternative above this cannot refine to < 2 px rms
CONTENDER_RATIO = 3.0  # ... unless the winner itself fits badly (a wrong basin)
_SAME_ANGLE_RAD = 1e-3
_SAME_RANGE_FRACTION = 1e-3


@dataclass(frozen=True)
class _Seed:
    T: NDArray[np.float64]
    iterations: int
    converged: bool
    reference: int  # index of the model point used as POSIT's P0


@dataclass(frozen=True)
class _Solution:
    T: NDArray[np.float64]
    residuals: NDArray[np.float64]  # (N,2) px
    rms: float
    seed: _Seed


def _rms(residuals: NDArray[np.float64]) -> float:
    return math.sqrt(float(np.vdot(residuals, residuals)) / len(residuals))


_COS_SAME_ANGLE = math.cos(_SAME_ANGLE_RAD)


def _same_pose(A: NDArray[np.float64], B: NDArray[np.float64]) -> bool:
    cos_angle = 0.5 * (float((A[:3, :3] * B[:3, :3]).sum()) - 1.0)
    if cos_angle < _COS_SAME_ANGLE:
        return False
    a, b = A[:3, 3].tolist(), B[:3, 3].tolist()
    return math.dist(a, b) <= _SAME_RANGE_FRACTION * math.hypot(*a)


class _Problem:
    """One solve: validated inputs and the arrays OpenCV wants, prepared once."""

    def __init__(
        self, object_points_mm: ArrayLike, image_points_px: ArrayLike, camera: CameraModel
    ) -> None:
        self.model = object_model(object_points_mm)
        self.xy = normalised_image_points(image_points_px, camera, self.model.n_points)
        self.obj = self.model.points_mm
        self.img = np.ascontiguousarray(image_points_px, dtype=float).reshape(-1, 2)
        self.camera = camera
        self.K, self.dist = camera_arrays(camera)
        tolerance_px = PLANAR_SEED_TOLERANCE_PX if self.model.planar else SEED_TOLERANCE_PX
        self.tolerance = tolerance_px / (0.5 * (camera.fx + camera.fy))
        self.raw_alternative: tuple[NDArray[np.float64], float] | None = None
        self.branch_rms: float | None = None  # raw rms of the losing coplanar branch

    def seeds(self, reference: int) -> list[_Seed]:
        """POSIT seeds with model point ``reference`` as P0 (both branches if planar)."""
        model: ObjectModel = self.model
        xy = self.xy
        if reference:
            model = object_model(np.roll(self.obj, -reference, axis=0))
            xy = np.roll(xy, -reference, axis=0)
        if model.planar:
            img = np.roll(self.img, -reference, axis=0) if reference else self.img
            # The losing branch is only a candidate for the alternative (the mirrored pose is
            # the better one), so it is not followed once it is behind a converged winner.
            result = posit_coplanar(
                model, xy, img, self.camera, SEED_MAX_ITERATIONS, self.tolerance, 1.0
            )
            seeds = [_Seed(result.T_camera_target, result.iterations, result.converged, reference)]
            self.branch_rms = None
            if result.alternative is not None:
                self.branch_rms = result.alternative[1]
                if self.raw_alternative is None:
                    self.raw_alternative = result.alternative
                seeds.append(
                    _Seed(result.alternative[0], result.iterations, result.converged, reference)
                )
            return seeds
        T, iterations, converged = posit_general(model, xy, SEED_MAX_ITERATIONS, self.tolerance)
        if not all_in_front(T, model.points_mm):
            raise BehindCameraError(
                "POSIT put part of the target behind the camera: the image points probably do "
                "not match the model (check the correspondence)"
            )
        return [_Seed(T, iterations, converged, reference)]

    def refine(self, seed: _Seed) -> _Solution | None:
        """LM from the seed on the measured points; None if the refined pose puts part of the
        target behind the camera."""
        T, residuals = refine_fit(self.obj, self.img, self.K, self.dist, seed.T)
        if not all_in_front(T, self.obj):
            return None
        return _Solution(T, residuals, _rms(residuals), seed)

    def candidates(self, reference: int) -> list[_Solution]:
        """Refined poses from the seeds with model point ``reference`` as POSIT's P0.

        Planar models have two local minima. Besides the better coplanar branch, the other
        branch and the mirror of the refined pose (more reliable than the other branch, which
        often drifts into the same basin) are candidates for the second one; each costs a
        projection to score raw. The better of them is always refined: at close range POSIT's
        branch can end in a spurious minimum that fits to a fraction of a pixel, whose mirror
        reprojects tens of pixels off and still leads to the true pose (seen: 0.68 px rms,
        55 mm off, mirror 8 px raw). The other is refined only when the first fell into the
        winner's basin and its raw rms makes it a contender (below CONTENDER_RAW_RMS_PX, or
        within CONTENDER_RATIO of the refined winner; any, when the winner itself fits worse
        than RETRY_RMS_PX).
        """
        seeds = self.seeds(reference)
        first = self.refine(seeds[0])
        out = [] if first is None else [first]
        if not self.model.planar:
            return out
        base_T = seeds[0].T if first is None else first.T
        mirror_T = mirrored_pose(base_T, self.obj, self.model.normal, self.model.centre_mm)
        options = [(reprojection_rms_px(mirror_T, self.obj, self.img, self.camera), mirror_T)]
        if len(seeds) > 1 and self.branch_rms is not None:
            options.append((self.branch_rms, seeds[1].T))
        options.sort(key=lambda o: o[0])
        # A winner that fits badly may sit in a wrong basin (strong perspective traps every
        # POSIT seed there): then every alternative seed is worth a refinement.
        limit = math.inf if first is None or first.rms > RETRY_RMS_PX else max(
            CONTENDER_RAW_RMS_PX, CONTENDER_RATIO * first.rms)
        bookkeeping = astuple_seed(seeds[0])
        for k, (raw_rms, T) in enumerate(options):
            if k and raw_rms > limit:
                break
            solution = self.refine(_Seed(T, *bookkeeping))
            if solution is None:
                continue
            out.append(solution)
            if first is None or not _same_pose(solution.T, first.T):
                break
        return out

    def solutions(self, references: range) -> tuple[list[_Solution], EstimationError | None]:
        """All refined candidates over these reference points, and the last seed failure."""
        out: list[_Solution] = []
        error: EstimationError | None = None
        for reference in references:
            try:
                out += self.candidates(reference)
            except EstimationError as exc:  # try the other seeds before giving up
                error = exc
        return out, error


def astuple_seed(seed: _Seed) -> tuple[int, bool, int]:
    """A seed's bookkeeping (iterations, converged, reference), for seeds derived from it."""
    return seed.iterations, seed.converged, seed.reference


def mirrored_pose(
    T: NDArray[np.float64], points_mm: NDArray[np.float64], normal: NDArray[np.float64],
    centre_mm: NDArray[np.float64] | None = None,
) -> NDArray[np.float64]:
    """The other planar pose with (almost) the same image: the target's depth reversed.

    Mirroring the target through the plane perpendicular to the line of sight v at its centre
    leaves the orthographic image unchanged; composing with the mirror through the model's own
    plane (normal n, which fixes every model point) makes it a rotation again:
    R' = (I - 2 v v^T) R (I - 2 n n^T). Under perspective this lands in the second local
    minimum's basin -- the seed coplanar POSIT misses when both its branches fall into one.
    """
    if centre_mm is None:
        centre_mm = points_mm.mean(axis=0)
    return _mirror(kernel_array(T), kernel_array(normal), kernel_array(centre_mm))


@numba.njit(cache=True, nogil=True)
def _mirror(
    T: NDArray[np.float64], normal: NDArray[np.float64], centre_mm: NDArray[np.float64]
) -> NDArray[np.float64]:
    """:func:`mirrored_pose`'s arithmetic, compiled (3x3 products: numpy's per-call overhead
    would be most of its cost)."""
    c = np.empty(3)
    for r in range(3):
        c[r] = T[r, 0] * centre_mm[0] + T[r, 1] * centre_mm[1] + T[r, 2] * centre_mm[2] + T[r, 3]
    norm = math.sqrt(c[0] * c[0] + c[1] * c[1] + c[2] * c[2])
    v = c / norm
    R1 = np.empty((3, 3))
    for j in range(3):  # (I - 2 v v^T) R
        vR = v[0] * T[0, j] + v[1] * T[1, j] + v[2] * T[2, j]
        for r in range(3):
            R1[r, j] = T[r, j] - 2.0 * v[r] * vR
    out = np.zeros((4, 4))
    for r in range(3):  # ... (I - 2 n n^T)
        Rn = R1[r, 0] * normal[0] + R1[r, 1] * normal[1] + R1[r, 2] * normal[2]
        for j in range(3):
            out[r, j] = R1[r, j] - 2.0 * Rn * normal[j]
    for r in range(3):
        out[r, 3] = c[r] - (out[r, 0] * centre_mm[0] + out[r, 1] * centre_mm[1]
                            + out[r, 2] * centre_mm[2])
    out[3, 3] = 1.0
    return out


def _distinct(solutions: list[_Solution]) -> list[_Solution]:
    """Solutions sorted by rms, with duplicates of a better pose removed."""
    kept: list[_Solution] = []
    for s in sorted(solutions, key=lambda s: s.rms):
        if not any(_same_pose(s.T, k.T) for k in kept):
            kept.append(s)
    return kept


def _unrefined_alternative(
    problem: _Problem, T_best: NDArray[np.float64], image_points: NDArray[np.float64]
) -> AlternativePose:
    """The better fitting of the other coplanar branch as POSIT left it (if it is not the
    winner's pose) and the mirrored pose, with its rms."""
    T = mirrored_pose(T_best, problem.obj, problem.model.normal, problem.model.centre_mm)
    mirror = AlternativePose(
        T, reprojection_rms_px(T, problem.obj, image_points, problem.camera))
    branch = problem.raw_alternative
    if branch is None or branch[1] >= mirror.rms_px or _same_pose_loose(branch[0], T_best):
        return mirror
    return AlternativePose(*branch)


def _same_pose_loose(A: NDArray[np.float64], B: NDArray[np.float64]) -> bool:
    """Rotations within ~1 deg: an unrefined seed of the winner's own basin."""
    return 0.5 * (float(np.sum(A[:3, :3] * B[:3, :3])) - 1.0) > math.cos(math.radians(1.0))


def solve_pose(
    object_points_mm: ArrayLike,
    image_points_px: ArrayLike,
    camera: CameraModel,
    *,
    dot_diameter_mm: float | None = None,
    correct_bias: bool = True,
    ambiguity_mm: float = MAX_DOT_MM,
    ambiguity_deg: float = MAX_DEG,
) -> PoseResult:
    """Pose of the target in the camera frame from matched image points (px).

    POSIT (coplanar POSIT for planar models) seeds LM refinement; see the module docstring for
    how wrong fixed points are escaped and when a planar pose is flagged ``ambiguous``. When
    ``dot_diameter_mm`` is given and ``correct_bias`` is true, the measured centroids are
    corrected for perspective bias at the solved pose and the pose is refined again; the
    corrected points are returned as ``image_points_px``.

    Raises TooFewBlobsError, DegenerateGeometryError, BehindCameraError (no seed or refined
    pose has the whole target in front of the camera) and NotConvergedError (the seed did not
    converge and the refined pose is still bad, rms > BAD_RMS_PX).
    """
    problem = _Problem(object_points_mm, image_points_px, camera)
    n = problem.model.n_points
    solutions, error = problem.solutions(range(1))
    if not solutions or min(s.rms for s in solutions) > RETRY_RMS_PX:
        more, error2 = problem.solutions(range(1, n))
        solutions += more
        error = error or error2
    if not solutions:
        if error is not None:
            raise error
        raise BehindCameraError(
            "every refined pose puts part of the target behind the camera: the image points "
            "probably do not match the model (check the correspondence)"
        )
    ranked = _distinct(solutions)
    planar = problem.model.planar
    best = ranked[0]
    alternative = ranked[1] if planar and len(ranked) > 1 else None
    notes: list[str] = []
    if best.seed.reference:
        notes.append(f"seeded with point {best.seed.reference} as POSIT reference")
    image_points = problem.img
    residuals = J = None
    if dot_diameter_mm is not None and correct_bias:
        # The bias is hundredths of a pixel, so the corrected points' minimum is one
        # first-order step from the solved pose (see shift_pose), not a re-run. The
        # alternative keeps its rms on the measured points; the correction cannot change the
        # ambiguity verdict, whose margin (1.5x) is far larger.
        bias = centroid_bias_px(best.T, problem.obj, dot_diameter_mm, camera)
        corrected = problem.img - bias
        T, shifted, J_shifted = shift_pose(problem.obj, corrected, problem.K, problem.dist,
                                           best.T)
        if all_in_front(T, problem.obj):
            image_points, residuals, J = corrected, shifted, J_shifted
            best = _Solution(T, residuals, _rms(residuals), best.seed)
            notes.append(f"perspective bias corrected (max {float(abs(bias).max()):.3f} px)")
    if residuals is None or J is None:
        _, residuals, J = pose_reprojection(problem.obj, image_points, problem.K, problem.dist,
                                            best.T)
    if not best.seed.converged and best.rms > BAD_RMS_PX:
        raise NotConvergedError(
            f"POSIT did not converge in {SEED_MAX_ITERATIONS} iterations and the refined pose "
            f"reprojects with {best.rms:.2f} px rms: check the correspondence and the intrinsics"
        )
    alt_pose: AlternativePose | None = None
    if alternative is not None:
        alt_pose = AlternativePose(alternative.T, alternative.rms)
    elif planar:
        alt_pose = _unrefined_alternative(problem, best.T, image_points)
        notes.append("no second local minimum: the alternative is the unrefined other branch")
    test = None if alt_pose is None else ambiguity_test(
        best.T, best.rms, alt_pose.T_camera_target, alt_pose.rms_px, problem.obj,
        max_dot_mm=ambiguity_mm, max_deg=ambiguity_deg)
    ambiguous = test is not None and test.ambiguous
    if test is not None:
        notes.append(
            f"alternative pose {'NOT ' if ambiguous else ''}separable: delta_chi2 "
            f"{test.delta_chi2:.1f} vs {test.threshold} at sigma {test.sigma_px:.3f} px, "
            f"{test.dot_shift_mm:.2f} mm / {test.rotation_deg:.2f} deg apart")
    return PoseResult(
        T_camera_target=best.T,
        rms_px=best.rms,
        residuals_px=np.sqrt((best.residuals * best.residuals).sum(axis=1)),
        iterations=best.seed.iterations,
        converged=best.seed.converged,
        ambiguous=ambiguous,
        alternative=alt_pose,
        covariance=covariance_from(residuals, J),
        image_points_px=image_points,
        notes=tuple(notes),
        ambiguity=test,
    )


def finish_pose(
    obj: NDArray[np.float64], img: NDArray[np.float64], camera: CameraModel,
    T_start: NDArray[np.float64],
) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
    """The refinement of a pose already near its minimum -> (T, residuals (N,2), J (2N,6)).

    The same LM as from a seed (see :mod:`estimator.refine`): from a nearby pose it stops after
    a few evaluations, at the minimum a refinement from farther away reaches.
    """
    K, dist = camera_arrays(camera)
    return refine_arrays(obj, img, K, dist, T_start)


def solve_pose_near(
    object_points_mm: ArrayLike,
    image_points_px: ArrayLike,
    camera: CameraModel,
    T_init: ArrayLike,
    *,
    dot_diameter_mm: float | None = None,
    correct_bias: bool = True,
    bias_px: ArrayLike | None = None,
) -> PoseResult:
    """Pose from matched points when a nearby pose is already known (tracking), no POSIT.

    LM from ``T_init`` on the measured points, then (with the bias correction) the first-order
    step to the corrected points' minimum (:func:`estimator.refine.shift_pose`): the same
    finish as :func:`solve_pose`, so a tracked frame gets the pose a full solve would give
    (to ~1e-6 mm). With ``bias_px`` (N,2: the
    perspective-bias offsets at a nearby pose, e.g. the tracked prediction) the points are
    corrected first and refined once -- half the cost; the offsets (hundredths of a pixel)
    differ from those at the solved pose by ~1e-3 px for mm-scale motion, which moves the
    pose by < 1e-3 mm, 30x below the noise-induced error.
    No alternative is searched (the track only starts from an unambiguous pose):
    ``alternative`` is None and ``ambiguous`` False. Raises
    BehindCameraError when the refined pose puts part of the target behind the camera.
    """
    obj = np.ascontiguousarray(object_points_mm, dtype=float).reshape(-1, 3)
    img = np.ascontiguousarray(image_points_px, dtype=float).reshape(-1, 2)
    if len(obj) != len(img) or len(obj) < 4:
        raise ValueError(f"need 4 or more matched points, got {len(obj)} and {len(img)}")
    if bias_px is not None:
        return near_pose_unchecked(obj, img, camera, np.asarray(T_init, dtype=float),
                               np.asarray(bias_px, dtype=float).reshape(-1, 2))
    T, residuals, J = finish_pose(obj, img, camera, np.asarray(T_init, dtype=float))
    notes = ["refined from the tracked pose"]
    image_points = img
    if dot_diameter_mm is not None and correct_bias and all_in_front(T, obj):
        bias = centroid_bias_px(T, obj, dot_diameter_mm, camera)
        image_points = img - bias
        K, dist = camera_arrays(camera)
        T, residuals, J = shift_pose(obj, image_points, K, dist, T)
        notes.append(f"perspective bias corrected (max {float(abs(bias).max()):.3f} px)")
    return _tracked_result(obj, T, residuals, J, image_points, tuple(notes))


def near_pose_unchecked(
    obj: NDArray[np.float64], img: NDArray[np.float64], camera: CameraModel,
    T_init: NDArray[np.float64], bias: NDArray[np.float64],
    matched_blobs: tuple[Blob, ...] = (), matched_ids: tuple[int, ...] = (),
    identity: str = "given", note: str | None = None,
) -> PoseResult:
    """:func:`solve_pose_near` with known bias offsets: one refinement, no validation.

    For the pipeline, whose arrays are already well formed: ``obj`` (N,3) and ``img`` (N,2)
    float64, ``bias`` (N,2) px (zeros for no correction). The matched blobs and ids go
    straight into the result.
    """
    image_points = img - bias
    T, residuals, J = finish_pose(obj, image_points, camera, T_init)
    notes = ("refined from the tracked pose, perspective bias at the predicted pose",)
    return _tracked_result(
        obj, T, residuals, J, image_points, notes if note is None else (*notes, note),
        matched_blobs, matched_ids, identity,
    )


def _tracked_result(
    obj: NDArray[np.float64], T: NDArray[np.float64], residuals: NDArray[np.float64],
    J: NDArray[np.float64], image_points: NDArray[np.float64], notes: tuple[str, ...],
    matched_blobs: tuple[Blob, ...] = (), matched_ids: tuple[int, ...] = (),
    identity: str = "given",
) -> PoseResult:
    """The result of a refinement from a tracked pose (no seed iterations, no alternative)."""
    if not all_in_front(T, obj):
        raise BehindCameraError(
            "the refined pose puts part of the target behind the camera: the tracked points "
            "no longer match the model"
        )
    return PoseResult(
        T_camera_target=T,
        rms_px=_rms(residuals),
        residuals_px=np.sqrt((residuals * residuals).sum(axis=1)),
        iterations=0,
        converged=True,
        covariance=covariance_from(residuals, J),
        matched_blobs=matched_blobs,
        matched_ids=matched_ids,
        image_points_px=image_points,
        notes=notes,
        identity=identity,
    )
