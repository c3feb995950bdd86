"""Tracking mode: look for each dot only in a small window around where it should be now.

Between consecutive frames a dot moves a few pixels, so labelling a window of a few dot
diameters around each dot is far cheaper than the full frame (no full-frame pass at all).
Each dot gets its own window (windows may overlap, see :func:`estimator.blobs.dots_in_rois`)
and takes the region nearest to its prediction.
The caller predicts where the dots are (the pipeline projects the model with the pose
extrapolated from the last two frames); without a prediction the last centres plus their
last pixel velocity are used. Any doubt (a dot not found, two windows claiming one blob, a
shape that changed) reports the track lost, and the caller falls back to a full search.

The threshold follows the dots' own grey levels: each frame's windows are thresholded at the
last frame's mid level of the tracked dots, halfway between their core and their background
(the kernel measures both with each centre). A dot's weighted centre still leans a little on
where its region ends (the rim and the background ring are cut from it: ~3e-5 px per grey
level for dots of ~200 px, ~2e-4 px for ~60 px), so a threshold held for a whole track --
one frame's Otsu level, off by several grey levels from the next track's -- would shift every
centre of that track alike, by a pattern that changes from one track to the next, which no
averaging over the track removes. The mid level measured moves by < 0.1 level per level of
threshold, so the threshold settles within two frames on a level set by the scene, and the
frame-to-frame brightness only adds noise that averages out. A fixed grey level chosen by the
caller is kept as it is (``follow_levels`` False).
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
from numpy.typing import NDArray

from estimator.blobs import BlobFilter, Detection, Polarity, dots_in_rois
from estimator.result import Blob


class BlobTracker:
    """Follows a set of already identified blobs from frame to frame."""

    def __init__(
        self, polarity: Polarity, filt: BlobFilter | None = None, margin_px: float = 12.0
    ) -> None:
        """``margin_px``: how far (px) beyond the prediction a dot may be."""
        self.polarity: Polarity = polarity
        self.filt = filt if filt is not None else BlobFilter()
        self.margin_px = float(margin_px)
        self._blobs: tuple[Blob, ...] = ()
        self._velocity = np.zeros((0, 2))
        self.last_px = np.zeros((0, 2))  # centres of the tracked blobs in the last frame
        self._threshold = 0.0
        self.follow_levels = True
        self._halves = np.zeros(0)  # half size of each dot's window, px
        self._areas = np.zeros(0)  # area of each tracked dot in the last frame
        self.model_ids: tuple[int, ...] = ()

    @property
    def active(self) -> bool:
        return bool(self._blobs)

    @property
    def threshold(self) -> float:
        """The grey level the next frame's windows will be thresholded at."""
        return self._threshold

    def start(self, blobs: Sequence[Blob], model_ids: Sequence[int], threshold: float,
              follow_levels: bool = True) -> None:
        """Begin tracking identified blobs, thresholding at ``threshold`` first (the blobs'
        mid level, see the module doc); ``follow_levels`` False keeps it for the whole track."""
        if len(blobs) != len(model_ids):
            raise ValueError("need one model id per blob")
        self.follow_levels = bool(follow_levels)
        self._blobs = tuple(blobs)
        self.last_px = np.array([[b.u, b.v] for b in blobs], dtype=float).reshape(-1, 2)
        self.model_ids = tuple(int(i) for i in model_ids)
        self._velocity = np.zeros((len(blobs), 2))
        self._threshold = float(threshold)
        self._set_shapes(blobs)

    def _set_shapes(self, blobs: Sequence[Blob]) -> None:
        """Window half sizes (dot radius + 4 px + margin) and areas of the tracked dots."""
        self._halves = np.array([0.5 * max(b.major_axis_px, 4.0) for b in blobs]) + (
            4.0 + self.margin_px)
        self._areas = np.array([b.area for b in blobs])

    def reset(self) -> None:
        self._blobs = ()
        self.last_px = np.zeros((0, 2))
        self.model_ids = ()
        self._velocity = np.zeros((0, 2))
        self._halves = np.zeros(0)

    def predicted_px(self) -> NDArray[np.float64]:
        """Where each tracked dot should be in the next frame (constant pixel velocity)."""
        return self.last_px + self._velocity

    def track(
        self, image_u8: NDArray[np.uint8], predicted_px: NDArray[np.float64] | None = None
    ) -> list[Blob] | None:
        """The tracked blobs in the new frame (same order as started), or None when lost.

        ``predicted_px`` (N,2): where the caller expects each dot; default
        :meth:`predicted_px`.
        """
        if not self._blobs:
            return None
        n = len(self._blobs)
        pred = self.predicted_px() if predicted_px is None else np.asarray(predicted_px, float)
        if pred.shape != (n, 2) or not np.all(np.isfinite(pred)):
            return None
        h, w = image_u8.shape
        halves = self._halves[:, None]
        lo = np.maximum(pred - halves, 0.0)
        hi = np.minimum(pred + halves + 2.0, (w, h))
        rois = np.hstack((lo, hi)).astype(np.int64)
        found_all = dots_in_rois(image_u8, self.polarity, self.filt, self._threshold, rois)
        picked_ids = self._pick(found_all, pred)
        if picked_ids is None:
            return None
        if self.follow_levels:
            self._threshold = float(found_all.mid_levels[picked_ids].mean())
        found = found_all.blobs(picked_ids)
        pts = np.array([[b.u, b.v] for b in found])
        self._velocity = pts - self.last_px
        self._blobs = tuple(found)
        self._set_shapes(found)
        self.last_px = pts
        return found

    def _pick(self, found_all: Detection, pred: NDArray[np.float64]) -> list[int] | None:
        """The region each dot takes (the nearest to its prediction), or None when in doubt."""
        n = len(self._blobs)
        if len(found_all) < n:
            return None
        centres = found_all.mask_centres_px
        dx = pred[:, :1] - centres[:, 0]
        dy = pred[:, 1:] - centres[:, 1]
        d2 = dx * dx + dy * dy  # (dots, regions)
        picked_ids: list[int] = d2.argmin(axis=1).tolist()
        if len(set(picked_ids)) != n:
            return None  # two dots claim the same region
        reach2 = 2.0 * self._halves * self._halves
        if (d2.min(axis=1) > reach2).any():
            return None  # nothing where a dot should be (its window would have been empty)
        ratio = found_all.areas[picked_ids] / np.maximum(self._areas, 1e-9)
        if ((ratio < 0.5) | (ratio > 2.0)).any():
            return None  # a different object wandered into the window
        return picked_ids
