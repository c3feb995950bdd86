"""Dot detection on 8-bit grey frames: threshold, regions, shape filters, sub-pixel centres.

The fast path looks at every fourth pixel of every fourth row first: Otsu's threshold comes
from that sample (every other pixel of it: nearly the same threshold for a 64th of the
histogram work), and so do
the regions of interest -- the sample is thresholded and its 8-connected regions found, and
each region that is not too large to be a dot gives a padded box that holds it whole at full
resolution. Only those boxes are labelled at full resolution, so a dot gets exactly the region
(and centre) a pass over the whole frame would give; when dots may be too small to leave a
sampled pixel, the whole frame is labelled instead. Each region is measured while it is
labelled (area, second moments, the convex hull of its pixel squares), the shape filters run
cheapest first, and only the survivors get the expensive part: a grey-level weighted centre of
gravity whose weights are each pixel's contrast against the local background, which uses the
anti-aliased rim the binary mask alone would throw away and does not depend on the global
threshold. All of it runs compiled (:mod:`estimator.regions`): one or two calls per frame.
A local (adaptive) threshold is available for strongly uneven lighting; it thresholds the whole
frame with OpenCV, so it is several times slower and opt-in.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Literal

import cv2
import numpy as np
from numpy.typing import NDArray

from estimator import regions
from estimator.arrays import kernel_array
from estimator.result import Blob

Polarity = Literal["dark", "light"]
ThresholdSpec = float | Literal["otsu", "adaptive"] | None

COARSE_STEP = 4  # subsampling of the frame for Otsu and for locating the candidate dots
_COARSE_PAD_PX = 2 * COARSE_STEP  # a region reaches < one step beyond its sampled pixels
_NO_MASK = np.zeros((1, 1), np.uint8)
# A frame whose sampled grey levels span less than this (the tails of SPREAD_TAIL cut) shows no
# dot: a covered lens with its sensor noise spans about 7 sigma (10 levels at sigma 1.5); the
# faintest dot the threshold separates from its plate is several times the noise apart.
MIN_SPREAD_GREY = 16.0
SPREAD_TAIL = 2e-4
INERTIA_MARGIN = 0.85  # of cos(max tilt): small ellipses' minor axes are quantised


@dataclass(frozen=True)
class BlobFilter:
    """Which regions count as dots: perspective-aware, so a dot seen obliquely still counts.

    A circular dot tilted by t images as an ellipse with axis ratio ~cos(t), so the shape test
    is how well the region fits an ellipse (``max_ellipse_error``, see
    :mod:`estimator.regions`) and how convex it is (``min_fill_ratio``), with the elongation
    limited by ``max_tilt_deg`` (inertia ratio >= 0.85 cos(max_tilt_deg), the 0.85 for the
    pixel grid's effect on small minor axes) unless ``min_inertia_ratio`` is set. Circularity
    (4 pi A / P^2) drops with the tilt (0.68 for a perfect ellipse at 70 deg, ~0.5 for a small
    pixelated one), so it is only a filter when ``min_circularity`` is set. Lines fail the
    inertia ratio, frames, rings and text the fill ratio, specks the area.
    """

    min_area_px: float = 12.0
    max_area_px: float = 20000.0
    min_circularity: float = 0.0
    min_inertia_ratio: float | None = None
    min_fill_ratio: float = 0.85
    max_tilt_deg: float = 70.0
    max_ellipse_error: float = 0.085

    def __post_init__(self) -> None:
        if not 0 < self.min_area_px < self.max_area_px:
            raise ValueError(
                f"need 0 < min_area_px < max_area_px, got {self.min_area_px}, {self.max_area_px}"
            )
        for name in ("min_circularity", "min_inertia_ratio", "min_fill_ratio"):
            v = getattr(self, name)
            if v is not None and not 0.0 <= v <= 1.0:
                raise ValueError(f"{name} must be in [0, 1], got {v}")
        if not 0.0 <= self.max_tilt_deg < 90.0:
            raise ValueError(f"max_tilt_deg must be in [0, 90), got {self.max_tilt_deg}")
        if not self.max_ellipse_error > 0.0:
            raise ValueError(f"max_ellipse_error must be positive, got {self.max_ellipse_error}")

    @property
    def inertia_limit(self) -> float:
        """The smallest inertia ratio (minor/major axis) accepted."""
        if self.min_inertia_ratio is not None:
            return self.min_inertia_ratio
        return INERTIA_MARGIN * math.cos(math.radians(self.max_tilt_deg))


def threshold_spec(value: object) -> ThresholdSpec:
    """A detector's ``threshold`` option checked: None, "otsu", "adaptive" or a grey level."""
    if value is None or value in ("otsu", "adaptive"):
        return value
    if isinstance(value, (int, float)) and not isinstance(value, bool):
        return float(value)
    raise ValueError(f'threshold must be a grey level, "otsu" or "adaptive", got {value!r}')


def _check_image(image_u8: NDArray[np.uint8]) -> NDArray[np.uint8]:
    img = np.asarray(image_u8)
    if img.dtype != np.uint8 or img.ndim != 2:
        raise ValueError(f"expected an 8-bit grey image (HxW uint8), got {img.dtype} {img.shape}")
    return np.ascontiguousarray(img)


def adaptive_binarize(
    image_u8: NDArray[np.uint8], polarity: Polarity, block_px: int = 51, offset: float = 15.0
) -> NDArray[np.uint8]:
    """Threshold against the local mean (for strongly uneven light): slower, but robust."""
    kind = cv2.THRESH_BINARY_INV if polarity == "dark" else cv2.THRESH_BINARY
    block = block_px | 1
    return np.asarray(
        cv2.adaptiveThreshold(image_u8, 255, cv2.ADAPTIVE_THRESH_MEAN_C, kind, block, offset),
        dtype=np.uint8,
    )


class Detection:
    """Dots found in a frame, as the kernel's rows (see :mod:`estimator.regions`); Blob objects
    are built only for the rows asked for (the tracker keeps a few of many)."""

    __slots__ = ("rows",)

    def __init__(self, rows: NDArray[np.float64]) -> None:
        self.rows = rows

    def __len__(self) -> int:
        return len(self.rows)

    @property
    def mask_centres_px(self) -> NDArray[np.float64]:
        """(N,2) centroid of each binary region."""
        return self.rows[:, regions.MASK_U:regions.MASK_V + 1]

    @property
    def centres_px(self) -> NDArray[np.float64]:
        """(N,2) weighted centre of each dot (a copy: contiguous, the caller's to keep)."""
        return self.rows[:, regions.U:regions.V + 1].copy()

    @property
    def areas(self) -> NDArray[np.float64]:
        return self.rows[:, regions.AREA]

    @property
    def mid_levels(self) -> NDArray[np.float64]:
        """(N,) grey level halfway between each dot's core and its local background."""
        return self.rows[:, regions.MID_LEVEL]

    def blobs(self, indices: list[int] | None = None) -> list[Blob]:
        """Blobs of all rows, or of the rows at ``indices`` in that order."""
        fields = regions.ELLIPSE + 1  # columns U..ELLIPSE are Blob's fields, in order
        rows = self.rows[:, :fields] if indices is None else self.rows[indices, :fields]
        return [Blob(*row) for row in rows.tolist()]


def dots_in_rois(
    image_u8: NDArray[np.uint8], polarity: Polarity, filt: BlobFilter, threshold: float,
    rois: NDArray[np.int64], mask_u8: NDArray[np.uint8] | None = None,
) -> Detection:
    """The dots wholly inside any of the given regions of interest (K,4: x0, y0, x1, y1 with the
    end exclusive; they may overlap), thresholded at ``threshold`` -- or, with ``mask_u8``
    (the frame's binary mask), wherever the mask is set."""
    image = kernel_array(image_u8, np.uint8)
    mask = _NO_MASK if mask_u8 is None else kernel_array(mask_u8, np.uint8)
    return Detection(regions.find_dots(
        image, mask, mask_u8 is not None, float(threshold),
        polarity == "dark", kernel_array(rois, np.int64), filt.min_area_px,
        filt.max_area_px, filt.min_circularity, filt.inertia_limit, filt.min_fill_ratio,
        filt.max_ellipse_error,
    ))


def grey_spread(sample_u8: NDArray[np.uint8]) -> float:
    """Grey levels between the darkest and the brightest pixels of ``sample_u8``, the
    SPREAD_TAIL of each end left out (a hot pixel or two is no contrast)."""
    hist = cv2.calcHist([sample_u8], [0], None, [256], [0, 256]).ravel()
    cum = np.cumsum(hist)
    tail = max(1.0, float(cum[-1]) * SPREAD_TAIL)
    return float(np.searchsorted(cum, cum[-1] - tail) - np.searchsorted(cum, tail))


def _whole_frame(image_u8: NDArray[np.uint8]) -> NDArray[np.int64]:
    return np.array([[0, 0, image_u8.shape[1], image_u8.shape[0]]], np.int64)


def detect_blobs_thresholded(
    image_u8: NDArray[np.uint8],
    polarity: Polarity = "dark",
    filt: BlobFilter | None = None,
    threshold: ThresholdSpec = None,
    *,
    coarse: bool = True,
) -> tuple[list[Blob], float | None]:
    """:func:`detect_blobs` that also returns the global threshold it used (None if adaptive),
    so the tracker can reuse it in its windows and find the very same regions.

    With a global threshold and ``coarse`` (the default), the subsampled frame first locates
    the regions of interest that can hold dots, and only those are labelled at full
    resolution; ``coarse=False`` always labels the whole frame (same dots, same centres).
    """
    found, thr = detect_dots(image_u8, polarity, filt, threshold, coarse=coarse)
    return found.blobs(), thr


Window = tuple[int, int, int, int]  # x0, y0, x1, y1 in px, the end exclusive


def detect_dots(
    image_u8: NDArray[np.uint8],
    polarity: Polarity = "dark",
    filt: BlobFilter | None = None,
    threshold: ThresholdSpec = None,
    *,
    coarse: bool = True,
    window: Window | None = None,
) -> tuple[Detection, float | None]:
    """:func:`detect_blobs_thresholded` with the dots as a :class:`Detection`: the pipeline
    builds Blob objects only for the dots it matches.

    ``window``: only the dots wholly inside it. The threshold still comes from the whole
    frame (the same sample, a few milliseconds even at 12 MP), so a dot inside the window gets
    exactly the region and centre the whole frame's pass gives it; only the labelling, which
    costs in proportion to the area, is confined to the window."""
    img = _check_image(image_u8)
    if polarity not in ("dark", "light"):
        raise ValueError(f'polarity must be "dark" or "light", got {polarity!r}')
    f = filt if filt is not None else BlobFilter()
    if threshold == "adaptive":
        mask = adaptive_binarize(img, polarity)
        area = _whole_frame(img) if window is None else _clip_rois(None, window, img.shape)
        return dots_in_rois(img, polarity, f, 0.0, area, mask), None
    sample = np.ascontiguousarray(img[::COARSE_STEP, ::COARSE_STEP])
    kind = cv2.THRESH_BINARY_INV if polarity == "dark" else cv2.THRESH_BINARY
    if threshold is None or threshold == "otsu":
        # Otsu from every other sample pixel (a 64th of the frame): the same threshold to a
        # grey level or so, for a quarter of the histogram work.
        thr = regions.otsu_threshold(sample, 2)
    else:
        thr = float(threshold)
    if grey_spread(sample) < MIN_SPREAD_GREY:
        # a featureless frame (a covered lens, darkness): no dot to find, and thresholding its
        # noise would make every other pixel a candidate and label the whole frame twice
        return Detection(np.zeros((0, regions.N_COLUMNS))), thr
    sample_mask = cv2.threshold(sample, thr, 255, kind)[1]
    sample_u8: NDArray[np.uint8] = np.asarray(sample_mask, dtype=np.uint8)
    rois = _coarse_rois(sample_u8, f, img.shape) if coarse else None
    if window is not None:
        rois = _clip_rois(rois, window, img.shape)
    return dots_in_rois(img, polarity, f, thr, _whole_frame(img) if rois is None else rois), thr


def _clip_rois(rois: NDArray[np.int64] | None, window: Window, shape: tuple[int, ...]
               ) -> NDArray[np.int64]:
    """The regions of interest cut to the window (None: the window itself). A region cut by
    the window's edge touches its ROI's border and is dropped, as a dot cut by the frame's
    edge is."""
    height, width = shape[:2]
    x0, y0, x1, y1 = (int(v) for v in window)
    x0, y0, x1, y1 = max(x0, 0), max(y0, 0), min(x1, width), min(y1, height)
    if rois is None:
        return np.array([[x0, y0, max(x1, x0), max(y1, y0)]], np.int64)
    out = np.column_stack((np.maximum(rois[:, 0], x0), np.maximum(rois[:, 1], y0),
                           np.minimum(rois[:, 2], x1), np.minimum(rois[:, 3], y1)))
    keep = (out[:, 2] > out[:, 0]) & (out[:, 3] > out[:, 1])
    return np.ascontiguousarray(out[keep] if keep.any() else out[:0], dtype=np.int64)


def _coarse_rois(
    sample_mask: NDArray[np.uint8], filt: BlobFilter, shape: tuple[int, ...]
) -> NDArray[np.int64] | None:
    """Regions of interest (K,4: x0, y0, x1, y1) that hold every possible dot, from the
    thresholded sample (every COARSE_STEP-th pixel of every COARSE_STEP-th row).

    Each region of the sample that is not too large to be a dot gives its bounding box,
    scaled back and padded by _COARSE_PAD_PX, so every dot that has a sampled pixel lies
    wholly inside a ROI and gets exactly the region (and centre) a full-frame pass would
    give. None -- label the whole frame -- when a candidate is a single sampled pixel (dots
    that small may have siblings no sample pixel hit) or there is no candidate.
    """
    contours, hierarchy = cv2.findContours(sample_mask, cv2.RETR_CCOMP,
                                           cv2.CHAIN_APPROX_SIMPLE)
    if hierarchy is None:
        return None
    step, pad = COARSE_STEP, _COARSE_PAD_PX
    too_big = 8.0 * filt.max_area_px / (step * step)  # bounding box, in sample pixels
    height, width = shape
    boxes = []
    for c, parent in zip(contours, hierarchy[0][:, 3].tolist(), strict=True):
        if parent >= 0:
            continue  # a hole
        x, y, w, h = cv2.boundingRect(c)
        if w * h > too_big:
            continue  # a frame, a long line, a plate: no dot
        if w * h <= 1:
            return None
        boxes.append((max(x * step - pad, 0), max(y * step - pad, 0),
                      min((x + w) * step + pad, width), min((y + h) * step + pad, height)))
    return np.array(boxes, np.int64) if boxes else None


def detect_blobs(
    image_u8: NDArray[np.uint8],
    polarity: Polarity = "dark",
    *,
    min_area_px: float = 12.0,
    max_area_px: float = 20000.0,
    min_circularity: float = 0.0,
    min_inertia_ratio: float | None = None,
    min_fill_ratio: float = 0.85,
    max_tilt_deg: float = 70.0,
    max_ellipse_error: float = 0.085,
    threshold: ThresholdSpec = None,
) -> list[Blob]:
    """Dark (or light) roughly elliptical dots of the frame with sub-pixel centres.

    ``threshold``: None/"otsu" (global Otsu, the fast default), "adaptive" (local mean; for
    strongly uneven lighting) or a grey level. Dots seen up to ``max_tilt_deg`` off-axis pass;
    lines, frames, text and specks fail the area, fill-ratio (region / convex hull),
    ellipse-fit or inertia-ratio (minor/major axis) filters (see :class:`BlobFilter`). Raises
    ValueError for a non-8-bit or non-grey image.
    """
    filt = BlobFilter(min_area_px, max_area_px, min_circularity, min_inertia_ratio,
                      min_fill_ratio, max_tilt_deg, max_ellipse_error)
    return detect_blobs_thresholded(image_u8, polarity, filt, threshold)[0]
