"""Search windows: where in the next frame to look for the dots after a frame that showed them.

A full search labels the whole frame; on a 12 MP sensor that is 12 million pixels for a plate
that covers a few hundred thousand. When the dots were seen a moment ago, they are near where
they were: a window around the last dots, wide enough for the dots themselves and for the image
motion since, holds them all, and labelling only the window costs in proportion to its area.
What the motion can have been is the caller's knowledge (the arm's speed, the camera's mount);
this module only turns a margin into a window and says when a window is not worth it.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike

from estimator.blobs import Window

MAX_AREA_FRACTION = 0.5  # a window larger than this part of the frame saves too little


def search_window(points_px: ArrayLike, margin_px: float, width: int, height: int
                  ) -> Window | None:
    """The box around ``points_px`` (N, 2) grown by ``margin_px`` on every side, cut to the
    frame (x0, y0, x1, y1, the end exclusive); None when it would cover more than
    ``MAX_AREA_FRACTION`` of the frame (the full search costs little more) or there are no
    finite points."""
    p = np.asarray(points_px, dtype=float).reshape(-1, 2)
    if not len(p) or not np.all(np.isfinite(p)) or not np.isfinite(margin_px) or margin_px < 0:
        return None
    lo = np.floor(p.min(axis=0) - margin_px)
    hi = np.ceil(p.max(axis=0) + margin_px) + 1
    x0, y0 = int(max(lo[0], 0)), int(max(lo[1], 0))
    x1, y1 = int(min(hi[0], width)), int(min(hi[1], height))
    if x1 <= x0 or y1 <= y0:
        return None
    if (x1 - x0) * (y1 - y0) > MAX_AREA_FRACTION * width * height:
        return None
    return (x0, y0, x1, y1)


def inside_window(points_px: ArrayLike, window: Window, clearance_px: float) -> bool:
    """Whether every point lies at least ``clearance_px`` inside the window: a dot centred
    there lies wholly inside it, so the window's search would have found it if the whole
    frame's search could."""
    p = np.asarray(points_px, dtype=float).reshape(-1, 2)
    x0, y0, x1, y1 = window
    c = float(clearance_px)
    return bool(np.all((p[:, 0] >= x0 + c) & (p[:, 0] <= x1 - 1 - c)
                       & (p[:, 1] >= y0 + c) & (p[:, 1] <= y1 - 1 - c)))
