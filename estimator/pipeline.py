"""Frame -> target pose: detect blobs, match them to the dots, solve, then track.

The first frame (and any frame after the track is lost) gets the full search: threshold the
whole frame, match blobs to dots by hypothesise-and-verify, solve. While the pose keeps
fitting, later frames skip all of that: the model is projected with the pose extrapolated from
the last two frames, each dot is looked for only in a small window around its prediction (the
ids come from the track, so there is no correspondence step), and the pose is refined from the
prediction instead of seeded by POSIT -- once: the points are corrected with the
perspective-bias offsets at the predicted pose (they change by ~1e-3 px between frames) and
refined by one LM run from the prediction (:func:`estimator.solve.near_pose_unchecked`). That
gives the full search's pose to < 1e-3 mm, for a fraction of the full search's cost.

Dot identities: the track keeps each dot's identity by continuity, so a symmetric layout --
whose fresh full search is ``ambiguous`` with its equivalent poses -- is tracked like any
other and its labels never flip between frames. When the track is lost, the next full search
keeps the labelling nearest the last pose (for up to ``PRIOR_MAX_FRAMES`` frames). Each result
says how its identities were resolved (``identity``: "unique", "symmetry", "continuity",
"ambiguous").
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np
from numpy.typing import NDArray

from estimator.ambiguity import MAX_DEG, MAX_DOT_MM
from estimator.bias import centroid_bias_px
from estimator.blobs import BlobFilter, Polarity, ThresholdSpec, detect_dots
from estimator.camera import CameraModel
from estimator.correspondence import match_blobs
from estimator.errors import EstimationError, TooFewBlobsError
from estimator.refine import camera_arrays
from estimator.result import Blob, PoseResult
from estimator.solve import near_pose_unchecked
from estimator.target import Target
from estimator.tracking import BlobTracker

_TRACK_MAX_RMS_PX = 1.0  # a tracked pose fitting worse than this triggers a full search
PRIOR_MAX_FRAMES = 30  # frames after a pose that its labelling still guides a full search


def _threshold_spec(value: object) -> ThresholdSpec:
    if value is None or value in ("otsu", "adaptive"):
        return value
    if isinstance(value, (int, float)) and not isinstance(value, bool):
        return float(value)
    raise ValueError(f'threshold must be a grey level, "otsu" or "adaptive", got {value!r}')


class Estimator:
    """Pose of one target in frames of one camera, with tracking between calls.

    ``detector_options`` are those of :func:`estimator.detect_blobs` (``min_area_px``,
    ``max_area_px``, ``min_circularity``, ``min_inertia_ratio``, ``min_fill_ratio``,
    ``threshold``, ``max_tilt_deg``, ``max_ellipse_error``); the polarity comes from the
    target. ``ambiguity_mm`` / ``ambiguity_deg``: how far an alternative pose must be from the
    chosen one at the dots to count as a different answer (see :mod:`estimator.ambiguity`).
    """

    def __init__(
        self,
        camera: CameraModel,
        target: Target,
        *,
        tracking: bool = True,
        max_missing: int = 1,
        correct_bias: bool = True,
        track_margin_px: float = 12.0,
        ambiguity_mm: float = MAX_DOT_MM,
        ambiguity_deg: float = MAX_DEG,
        **detector_options: float | str | None,
    ) -> None:
        self.camera = camera
        self.target = target
        self.tracking = tracking
        self.max_missing = int(max_missing)
        self.correct_bias = correct_bias
        if not (ambiguity_mm > 0 and ambiguity_deg > 0):
            raise ValueError("ambiguity_mm and ambiguity_deg must be positive")
        self.ambiguity = (float(ambiguity_mm), float(ambiguity_deg))
        opts = dict(detector_options)
        self._threshold = _threshold_spec(opts.pop("threshold", None))
        try:
            self.filter = BlobFilter(**{k: float(v) for k, v in opts.items()})  # type: ignore[arg-type]
        except TypeError as err:
            raise ValueError(f"unknown detector option: {err}") from err
        self.polarity: Polarity = target.polarity
        self._tracker = BlobTracker(self.polarity, self.filter, track_margin_px)
        self.last_mode = "none"  # "full" or "tracking": how the last estimate was found
        self._T_last: NDArray[np.float64] | None = None  # poses of the last two tracked frames
        self._T_prev: NDArray[np.float64] | None = None
        self._track_obj = np.zeros((0, 3))  # model points of the tracked dots, in track order
        self._K, _ = camera_arrays(camera)
        self._distorted = camera.has_distortion
        self._prior_T: NDArray[np.float64] | None = None  # last pose, for continuity
        self._prior_age = 0  # frames since that pose
        self._tracked_frames = 0  # consecutive tracked frames of the current track

    def reset(self) -> None:
        """Forget the track and the last pose: the next frame gets a fresh full search."""
        self._tracker.reset()
        self._prior_T = None

    @property
    def min_blobs(self) -> int:
        return max(4, self.target.n_points - self.max_missing)

    def estimate(self, frame_u8: NDArray[np.uint8]) -> PoseResult:
        """Pose of the target in this frame; raises a typed EstimationError when it cannot."""
        img = np.ascontiguousarray(frame_u8)
        if img.dtype != np.uint8 or img.ndim != 2:
            raise ValueError(f"expected an 8-bit grey frame (HxW uint8), got {img.dtype} "
                             f"{img.shape}")
        self._prior_age += 1
        if self._tracker.active:
            tracked = self._track(img)
            if tracked is not None:
                self._prior_T, self._prior_age = tracked.T_camera_target, 0
                return tracked
            self._tracker.reset()
        result = self._full_search(img)
        self._prior_T, self._prior_age = result.T_camera_target, 0
        return result

    def _predicted_pose(self) -> NDArray[np.float64]:
        """The last pose moved on by the last frame-to-frame motion (constant velocity)."""
        T_last, T_prev = self._T_last, self._T_prev
        assert T_last is not None and T_prev is not None
        if T_prev is T_last:  # first tracked frame: no motion known yet
            return T_last
        step = np.linalg.solve(T_prev, T_last)  # T_prev^-1 T_last, target frame
        return np.asarray(T_last @ step, dtype=np.float64)

    def _track(self, img: NDArray[np.uint8]) -> PoseResult | None:
        ids = self._tracker.model_ids
        T_pred = self._predicted_pose()
        obj = self._track_obj
        KT = self._K @ T_pred[:3]  # K folded into the pose: one product projects
        Q = obj @ KT[:, :3].T + KT[:, 3]
        if Q[:, 2].min() <= 0.0:  # K's last row is (0, 0, 1): Q's z is the depth
            return None
        if self._distorted:
            pred = self.camera.project(obj @ T_pred[:3, :3].T + T_pred[:3, 3])
        else:
            pred = Q[:, :2] / Q[:, 2:]
        blobs = self._tracker.track(img, pred)
        if blobs is None:
            return None
        pts = self._tracker.last_px
        # The bias offsets at the predicted pose (hundredths of a px, changing ~1e-3 px per
        # frame): one refinement on the corrected points replaces the full solve's two.
        bias = (centroid_bias_px(T_pred, obj, self.target.dot_diameter_mm, self.camera)
                if self.correct_bias else np.zeros_like(pts))
        try:
            pose = near_pose_unchecked(
                obj, pts, self.camera, T_pred, bias, tuple(blobs), ids, "continuity",
                f"dot identities kept by continuity (tracked frame {self._tracked_frames + 1} "
                "since the full search)")
        except EstimationError:
            return None
        if pose.rms_px > _TRACK_MAX_RMS_PX:
            return None
        self.last_mode = "tracking"
        self._T_prev, self._T_last = self._T_last, pose.T_camera_target
        self._tracked_frames += 1
        return pose

    def _full_search(self, img: NDArray[np.uint8]) -> PoseResult:
        found, threshold = detect_dots(img, self.polarity, self.filter, self._threshold)
        if len(found) < self.target.n_points:  # a dot too small for the coarse pass to see?
            found, threshold = detect_dots(
                img, self.polarity, self.filter, self._threshold, coarse=False
            )
        if len(found) < self.min_blobs:
            raise TooFewBlobsError(
                len(found), self.min_blobs,
                f"the target has {self.target.n_points} {self.polarity} dots",
            )
        pts = found.centres_px
        prior = self._prior_T if self._prior_age <= PRIOR_MAX_FRAMES else None
        corr = match_blobs(pts, self.target, self.camera, max_missing=self.max_missing,
                           correct_bias=self.correct_bias, prior_T=prior,
                           ambiguity=self.ambiguity)
        matched = found.blobs(list(corr.blob_indices))
        # A symmetric layout's labellings fit alike: any one is a consistent start, and the
        # track keeps it. Different matchings that fit alike are no start at all.
        if self.tracking and threshold is not None and corr.pose.identity != "ambiguous":
            self._tracked_frames = 0
            self._tracker.start(matched, corr.model_ids, threshold)
            self._track_obj = np.ascontiguousarray(self.target.points_mm[list(corr.model_ids)])
            self._T_last = self._T_prev = corr.pose.T_camera_target
        self.last_mode = "full"
        return self._finish(corr.pose, matched, corr.model_ids, pts[list(corr.blob_indices)])

    @staticmethod
    def _finish(
        pose: PoseResult, blobs: list[Blob], ids: tuple[int, ...], pts: NDArray[np.float64]
    ) -> PoseResult:
        return replace(pose, matched_blobs=tuple(blobs), matched_ids=tuple(ids),
                       image_points_px=pose.image_points_px if pose.image_points_px is not None
                       else pts)
