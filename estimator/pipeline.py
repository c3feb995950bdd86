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

A frame the track does not explain can still be searched near where the dots were: the caller
may pass a search window (``estimate(frame, window=...)``, see :mod:`estimator.window`); the
full search then runs inside it only (the threshold from the whole frame, so the dots it finds
have the whole frame's regions and centres), and the result stands only if every dot of the
target projects, at the pose found, wholly inside the window: a dot missing there is one the
whole frame's search would miss too (hidden, or off the plate's image), not one outside the
window. Anything else falls back to the full search of the whole frame (``last_mode``
"window" or "full"). Both skip the full-resolution pass (the one for dots too small for the
coarse pass to see; hundreds of milliseconds over a 12 MP frame, which a hidden dot would
otherwise trigger) when the dots were ``FINE_PASS_BELOW_PX`` or wider in the frame the window
comes from: dots that size leave several sampled pixels each, so the coarse pass finds every
one there is.

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
from estimator.blobs import (
    COARSE_STEP,
    BlobFilter,
    Polarity,
    Window,
    detect_dots,
    threshold_spec,
)
from estimator.camera import CameraModel
from estimator.correspondence import match_blobs
from estimator.errors import EstimationError, TooFewBlobsError
from estimator.refine import camera_arrays
from estimator.result import Blob, PoseResult
from estimator.solve import near_pose_unchecked
from estimator.target import Target
from estimator.tracking import BlobTracker
from estimator.window import inside_window

_TRACK_MAX_RMS_PX = 1.0  # a tracked pose fitting worse than this triggers a full search
PRIOR_MAX_FRAMES = 30  # frames after a pose that its labelling still guides a full search
FINE_PASS_BELOW_PX = 4.0 * COARSE_STEP  # dots narrower than this may need the fine pass
WINDOW_CLEARANCE_PX = 4.0  # beyond a dot's half axis: a dot centred further in is wholly inside


class _NotAllInWindow(Exception):
    """A windowed search missed a dot that may lie outside the window."""


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
        self._threshold = threshold_spec(opts.pop("threshold", None))
        try:
            self.filter = BlobFilter(**{k: float(v) for k, v in opts.items()})  # type: ignore[arg-type]
        except TypeError as err:
            raise ValueError(f"unknown detector option: {err}") from err
        self.polarity: Polarity = target.polarity
        self._tracker = BlobTracker(self.polarity, self.filter, track_margin_px)
        self.last_mode = "none"  # "full", "window" or "tracking": how the last was found
        self._T_last: NDArray[np.float64] | None = None  # poses of the last two tracked frames
        self._T_prev: NDArray[np.float64] | None = None
        self._track_obj = np.zeros((0, 3))  # model points of the tracked dots, in track order
        self._K, _ = camera_arrays(camera)
        self._distorted = camera.has_distortion
        self._prior_T: NDArray[np.float64] | None = None  # last pose, for continuity
        self._prior_age = 0  # frames since that pose
        self._tracked_frames = 0  # consecutive tracked frames of the current track
        self._min_dot_px = 0.0  # the narrowest matched dot's minor axis in the last result

    def reset(self) -> None:
        """Forget the track and the last pose: the next frame gets a fresh full search."""
        self._tracker.reset()
        self._prior_T = None
        self._min_dot_px = 0.0

    @property
    def min_blobs(self) -> int:
        return max(4, self.target.n_points - self.max_missing)

    def estimate(self, frame_u8: NDArray[np.uint8], window: Window | None = None
                 ) -> PoseResult:
        """Pose of the target in this frame; raises a typed EstimationError when it cannot.

        ``window`` (x0, y0, x1, y1 px): where the dots should be when the track does not
        explain the frame; searched before the whole frame (see the module doc)."""
        img = np.ascontiguousarray(frame_u8)
        if img.dtype != np.uint8 or img.ndim != 2:
            raise ValueError(f"expected an 8-bit grey frame (HxW uint8), got {img.dtype} "
                             f"{img.shape}")
        self._prior_age += 1
        if self._tracker.active:
            tracked = self._track(img)
            if tracked is not None:
                self._prior_T, self._prior_age = tracked.T_camera_target, 0
                self._min_dot_px = min((b.minor_axis_px for b in tracked.matched_blobs),
                                       default=0.0)
                return tracked
            self._tracker.reset()
        result, fine = None, True
        if window is not None:
            fine = self._min_dot_px < FINE_PASS_BELOW_PX
            try:
                result = self._full_search(img, window, fine=fine)
            except (EstimationError, _NotAllInWindow):
                result = None
        if result is None:
            result = self._full_search(img, fine=fine)
        self._prior_T, self._prior_age = result.T_camera_target, 0
        self._min_dot_px = min((b.minor_axis_px for b in result.matched_blobs), default=0.0)
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

    def _full_search(self, img: NDArray[np.uint8], window: Window | None = None, *,
                     fine: bool = True) -> PoseResult:
        found, threshold = detect_dots(img, self.polarity, self.filter, self._threshold,
                                       window=window)
        if fine and len(found) < self.target.n_points:  # a dot too small for the coarse pass?
            found, threshold = detect_dots(
                img, self.polarity, self.filter, self._threshold, coarse=False, window=window
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
        if window is not None and len(corr.model_ids) < self.target.n_points:
            self._check_window(corr.pose.T_camera_target, matched, window)
        # A symmetric layout's labellings fit alike: any one is a consistent start, and the
        # track keeps it. Different matchings that fit alike are no start at all.
        if self.tracking and threshold is not None and corr.pose.identity != "ambiguous":
            self._tracked_frames = 0
            # The track thresholds at the dots' own mid level (see estimator.tracking); a
            # grey level the caller fixed stays fixed.
            fixed = isinstance(self._threshold, float)
            level = threshold if fixed else float(
                found.mid_levels[list(corr.blob_indices)].mean())
            self._tracker.start(matched, corr.model_ids, level, follow_levels=not fixed)
            self._track_obj = np.ascontiguousarray(self.target.points_mm[list(corr.model_ids)])
            self._T_last = self._T_prev = corr.pose.T_camera_target
        self.last_mode = "full" if window is None else "window"
        return self._finish(corr.pose, matched, corr.model_ids, pts[list(corr.blob_indices)])

    def _check_window(self, T_camera_target: NDArray[np.float64], matched: list[Blob],
                      window: Window) -> None:
        """Every dot of the target, at the pose the window gave, wholly inside the window:
        the missing ones are then missing from the whole frame too."""
        Pc = self.target.points_mm @ T_camera_target[:3, :3].T + T_camera_target[:3, 3]
        if Pc[:, 2].min() <= 0.0:
            raise _NotAllInWindow
        half = 0.5 * max(b.major_axis_px for b in matched)
        if not inside_window(self.camera.project(Pc), window, half + WINDOW_CLEARANCE_PX):
            raise _NotAllInWindow

    @staticmethod
    def _finish(
        pose: PoseResult, blobs: list[Blob], ids: tuple[int, ...], pts: NDArray[np.float64]
    ) -> PoseResult:
        return replace(pose, matched_blobs=tuple(blobs), matched_ids=tuple(ids),
                       image_points_px=pose.image_points_px if pose.image_points_px is not None
                       else pts)
