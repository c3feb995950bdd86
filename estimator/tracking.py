"""Tracking mode: look for each dot only in a small window around where it should be now.

Between consecutive frames a dot moves a few pixels, so thresholding and tracing a window of
a few dot diameters around each dot is far cheaper than the full frame (no full-frame pass at
all). The windows of one target overlap or nearly touch, so they are traced as one region of
interest (their bounding box) and each dot takes the nearest region to its prediction.
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

from estimator.blobs import BlobFilter, Polarity, blobs_from_regions, dot_regions
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
        self.last_px = np.array([[b.u, b.v] for b in blobs], dtype=float).reshape(-1, 2)
        self.model_ids = tuple(int(i) for i in model_ids)
        self._velocity = np.zeros((len(blobs), 2))
        self._threshold = float(threshold)

    def reset(self) -> None:
        self._blobs = ()
        self.last_px = np.zeros((0, 2))
        self.model_ids = ()
        self._velocity = np.zeros((0, 2))

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
        # One region of interest around all the predictions (the dots of one target are close
        # together): one threshold and one contour pass instead of one per dot. Its regions are
        # the full frame's regions (same global threshold, each wholly inside the ROI). (Windows
        # copied side by side into one strip trace a fifth of the pixels: measured no faster.)
        pad = 4.0 + self.margin_px
        halves = [0.5 * max(b.major_axis_px, 4.0) + pad for b in self._blobs]
        reach = max(halves)
        (u0, v0), (u1, v1) = pred.min(axis=0).tolist(), pred.max(axis=0).tolist()
        x0, y0 = max(int(u0 - reach), 0), max(int(v0 - reach), 0)
        x1, y1 = min(int(u1 + reach) + 2, w), min(int(v1 + reach) + 2, h)
        if x1 - x0 < 4 or y1 - y0 < 4:
            return None
        mask = cv2.threshold(image_u8[y0:y1, x0:x1], self._threshold, 255, self._kind)[1]
        cands = dot_regions(cast(NDArray[np.uint8], mask), self.filt, offset=(x0, y0))
        if len(cands) < n:
            return None
        centres = np.array([c.mask_centre for c in cands])
        dx = pred[:, :1] - centres[:, 0]
        dy = pred[:, 1:] - centres[:, 1]
        d2 = dx * dx + dy * dy  # (dots, regions)
        picked_ids = d2.argmin(axis=1).tolist()
        if len(set(picked_ids)) != n:
            return None  # two dots claim the same region
        for best, half in zip(d2.min(axis=1).tolist(), halves, strict=True):
            if best > 2.0 * half * half:
                return None  # nothing where a dot should be (its window would have been empty)
        picked = [cands[k] for k in picked_ids]
        for blob, region in zip(self._blobs, picked, strict=True):
            if not 0.5 <= region.area / max(blob.area, 1e-9) <= 2.0:
                return None  # a different object wandered into the window
        found = blobs_from_regions(image_u8, picked, self.polarity)  # one batch for all dots
        if len(found) != n:
            return None
        pts = np.array([[b.u, b.v] for b in found])
        self._velocity = pts - self.last_px
        self._blobs = tuple(found)
        self.last_px = pts
        return found
