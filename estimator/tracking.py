"""Tracking mode: look for each dot only in a small window around where it should be now.

Between consecutive frames a dot moves a few pixels, so thresholding and tracing a window of
a few dot diameters per dot is far cheaper than the full frame (no full-frame pass at all).
The caller predicts where the dots are (the pipeline projects the model with the pose
extrapolated from the last two frames); without a prediction the last centres plus their
last pixel velocity are used. The windows reuse the global threshold of the last full search,
so a dot found in its window has exactly the outline, and hence exactly the centre, the full
search would give. Any doubt (a dot not found, two windows claiming one blob, a shape that
changed) reports the track lost, and the caller falls back to a full search, which also
re-estimates the threshold.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import cast

import cv2
import numpy as np
from numpy.typing import NDArray

from estimator.blobs import BlobFilter, Polarity, Region, blobs_from_regions, dot_regions
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
        self._threshold = 0.0
        self._kind = cv2.THRESH_BINARY_INV if polarity == "dark" else cv2.THRESH_BINARY
        self.model_ids: tuple[int, ...] = ()

    @property
    def active(self) -> bool:
        return bool(self._blobs)

    def start(self, blobs: Sequence[Blob], model_ids: Sequence[int], threshold: float) -> None:
        """Begin tracking identified blobs found with a global ``threshold``."""
        if len(blobs) != len(model_ids):
            raise ValueError("need one model id per blob")
        self._blobs = tuple(blobs)
        self.model_ids = tuple(int(i) for i in model_ids)
        self._velocity = np.zeros((len(blobs), 2))
        self._threshold = float(threshold)

    def reset(self) -> None:
        self._blobs = ()
        self.model_ids = ()
        self._velocity = np.zeros((0, 2))

    def predicted_px(self) -> NDArray[np.float64]:
        """Where each tracked dot should be in the next frame (constant pixel velocity)."""
        last = np.array([[b.u, b.v] for b in self._blobs], dtype=float).reshape(-1, 2)
        return last + self._velocity

    def track(
        self, image_u8: NDArray[np.uint8], predicted_px: NDArray[np.float64] | None = None
    ) -> list[Blob] | None:
        """The tracked blobs in the new frame (same order as started), or None when lost.

        ``predicted_px`` (N,2): where the caller expects each dot; default
        :meth:`predicted_px`.
        """
        if not self._blobs:
            return None
        pred = self.predicted_px() if predicted_px is None else np.asarray(predicted_px, float)
        if pred.shape != (len(self._blobs), 2) or not np.all(np.isfinite(pred)):
            return None
        h, w = image_u8.shape
        # One region of interest around all the predictions (the dots of one target are close
        # together): one threshold and one contour pass instead of one per dot. Its regions are
        # the full frame's regions (same global threshold, each wholly inside the ROI).
        halves = [0.5 * max(b.major_axis_px, 4.0) + 4.0 + self.margin_px for b in self._blobs]
        reach = max(halves)
        x0 = max(int(float(pred[:, 0].min()) - reach), 0)
        y0 = max(int(float(pred[:, 1].min()) - reach), 0)
        x1 = min(int(float(pred[:, 0].max()) + reach) + 2, w)
        y1 = min(int(float(pred[:, 1].max()) + reach) + 2, h)
        if x1 - x0 < 4 or y1 - y0 < 4:
            return None
        mask = cv2.threshold(image_u8[y0:y1, x0:x1], self._threshold, 255, self._kind)[1]
        cands = dot_regions(cast(NDArray[np.uint8], mask), self.filt, offset=(x0, y0))
        if not cands:
            return None
        centres = np.array([c.mask_centre for c in cands])
        d2 = ((pred[:, None, :] - centres[None, :, :]) ** 2).sum(axis=2)
        nearest = d2.argmin(axis=1).tolist()
        if len(set(nearest)) != len(nearest):
            return None  # two dots claim the same region
        picked: list[Region] = []
        for blob, k, half, dist2 in zip(self._blobs, nearest, halves,
                                        d2[np.arange(len(nearest)), nearest].tolist(),
                                        strict=True):
            best = cands[k]
            if dist2 > 2.0 * half * half:
                return None  # nothing where this dot should be (its window was empty)
            if not 0.5 <= best.area / max(blob.area, 1e-9) <= 2.0:
                return None  # a different object wandered into the window
            picked.append(best)
        found = blobs_from_regions(image_u8, picked, self.polarity)  # one batch for all dots
        if len(found) != len(picked):
            return None
        pts = np.array([[b.u, b.v] for b in found])
        gaps = np.linalg.norm(pts[:, None] - pts[None], axis=2) + np.eye(len(pts)) * 1e9
        if gaps.min() < 1.0:
            return None  # two windows locked onto the same blob
        last = np.array([[b.u, b.v] for b in self._blobs])
        self._velocity = pts - last
        self._blobs = tuple(found)
        return found
