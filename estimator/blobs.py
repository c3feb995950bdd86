"""Dot detection on 8-bit grey frames: threshold, contours, shape filters, sub-pixel centres.

The fast path takes every fourth pixel of every fourth row once: Otsu's threshold comes from
that sample (nearly the same threshold for a sixteenth of the histogram work), and so does the
window that can hold dots -- the sample is thresholded and traced (a sixteenth of the work), and
only the bounding box of its dot-sized regions, padded, is thresholded at full resolution.
Regions wholly inside that window have exactly their full-frame outlines, hence exactly the
full-frame centres; when dots may be too small to leave a sampled pixel, or the window would
be most of the frame, the whole frame is traced instead. Region outlines come from
cv2.findContours, area and shape from contour moments. Only the survivors get the
expensive part: a grey-level weighted centre of gravity whose weights are each pixel's contrast
against the local background, over the blob's padded bounding box restricted to its slightly
dilated region. That uses the anti-aliased rim too, which the binary mask alone would throw
away, and it is insensitive to the global threshold. A local (adaptive) threshold is available
for strongly uneven lighting, but it costs several times the global one at 1280x800, so it is
opt-in.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any, Literal

import cv2
import numpy as np
from numpy.typing import NDArray

from estimator.result import Blob

Polarity = Literal["dark", "light"]
ThresholdSpec = float | Literal["otsu", "adaptive"] | None
Contour = NDArray[Any]  # OpenCV point array (n, 1, 2) int32

_RIM_PX = 2  # the anti-aliased/blurred rim beyond the binary region that still carries weight
_DILATE = np.ones((2 * _RIM_PX + 1, 2 * _RIM_PX + 1), np.uint8)
_COARSE_STEP = 4  # subsampling of the frame for Otsu and for locating the candidate dots
_COARSE_PAD_PX = 2 * _COARSE_STEP  # a region reaches < one step beyond its sampled pixels
_COARSE_MAX_FRACTION = 0.4  # a candidate window larger than this: threshold the whole frame


@dataclass(frozen=True)
class BlobFilter:
    """Which regions count as dots. Defaults accept circles seen up to ~70 deg off-axis."""

    min_area_px: float = 12.0
    max_area_px: float = 20000.0
    min_circularity: float = 0.6
    min_inertia_ratio: float = 0.3
    min_fill_ratio: float = 0.85

    def __post_init__(self) -> None:
        if not 0 < self.min_area_px < self.max_area_px:
            raise ValueError(
                f"need 0 < min_area_px < max_area_px, got {self.min_area_px}, {self.max_area_px}"
            )
        for name in ("min_circularity", "min_inertia_ratio", "min_fill_ratio"):
            v = getattr(self, name)
            if not 0.0 <= v <= 1.0:
                raise ValueError(f"{name} must be in [0, 1], got {v}")


def _check_image(image_u8: NDArray[np.uint8]) -> NDArray[np.uint8]:
    img = np.asarray(image_u8)
    if img.dtype != np.uint8 or img.ndim != 2:
        raise ValueError(f"expected an 8-bit grey image (HxW uint8), got {img.dtype} {img.shape}")
    return img


def _subsample(image_u8: NDArray[np.uint8]) -> NDArray[np.uint8]:
    """Every ``_COARSE_STEP``-th pixel of every ``_COARSE_STEP``-th row (a contiguous copy)."""
    return np.ascontiguousarray(image_u8[::_COARSE_STEP, ::_COARSE_STEP])


def _otsu_of_sample(sample_u8: NDArray[np.uint8]) -> float:
    thr, _ = cv2.threshold(sample_u8, 0, 255, cv2.THRESH_BINARY | cv2.THRESH_OTSU)
    return float(thr)


def candidate_window(
    sample_u8: NDArray[np.uint8], polarity: Polarity, threshold: float, filt: BlobFilter,
    shape: tuple[int, int],
) -> tuple[int, int, int, int] | None:
    """The frame window (x0, y0, x1, y1) holding every possible dot, from the subsampled frame.

    Each region of the thresholded sample that is not too large to be a dot is a candidate;
    the window is their joint bounding box, scaled back and padded by ``_COARSE_PAD_PX``, so
    every dot that has a sampled pixel lies wholly inside it and gets exactly the outline (and
    centre) a full-frame pass would give. None -- search the whole frame -- when a candidate
    is a single sampled pixel (dots that small may have siblings no sample pixel hit), when
    there is no candidate, or when the window would not save much.
    """
    mask = binarize(sample_u8, polarity, threshold)
    contours, hierarchy = cv2.findContours(mask, cv2.RETR_CCOMP, cv2.CHAIN_APPROX_SIMPLE)
    if hierarchy is None:
        return None
    step = _COARSE_STEP
    too_big = 8.0 * filt.max_area_px / (step * step)  # bounding box, in sample pixels
    x0 = y0 = 1 << 30
    x1 = y1 = -1
    for c, parent in zip(contours, hierarchy[0][:, 3].tolist(), strict=True):
        if parent >= 0:
            continue  # a hole
        x, y, w, h = cv2.boundingRect(c)
        if w * h > too_big:
            continue  # a frame, a long line, a plate: no dot
        if w * h <= 1:
            return None
        x0, y0, x1, y1 = min(x0, x), min(y0, y), max(x1, x + w), max(y1, y + h)
    if x1 < 0:
        return None
    height, width = shape
    pad = _COARSE_PAD_PX
    win = (max(x0 * step - pad, 0), max(y0 * step - pad, 0),
           min(x1 * step + pad, width), min(y1 * step + pad, height))
    if (win[2] - win[0]) * (win[3] - win[1]) > _COARSE_MAX_FRACTION * width * height:
        return None
    return win


def binarize(
    image_u8: NDArray[np.uint8], polarity: Polarity, threshold: float
) -> NDArray[np.uint8]:
    """255 where the pixel looks like dot (darker/brighter than ``threshold``), else 0."""
    kind = cv2.THRESH_BINARY_INV if polarity == "dark" else cv2.THRESH_BINARY
    _, mask = cv2.threshold(image_u8, threshold, 255, kind)
    return np.asarray(mask, dtype=np.uint8)


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


def _region_area(contours: Sequence[Contour], hierarchy: list[list[int]], i: int) -> float:
    """Area of an outer contour minus its holes (RETR_CCOMP hierarchy)."""
    area = cv2.contourArea(contours[i])
    child = int(hierarchy[i][2])
    while child >= 0:
        area -= cv2.contourArea(contours[child])
        child = int(hierarchy[child][0])
    return float(area)


@dataclass(slots=True)
class Region:
    """A region that passed the shape filters; its grey-level centre is computed later."""

    contour: Contour  # frame coordinates
    rect: tuple[int, int, int, int]  # bounding box x, y, w, h (frame coordinates)
    area: float
    circularity: float
    inertia_ratio: float
    fill_ratio: float
    major_axis_px: float
    minor_axis_px: float
    angle_rad: float
    mask_centre: tuple[float, float]  # centroid of the binary region (for window matching)

    def blob(self, u: float, v: float) -> Blob:
        return Blob(u=u, v=v, area=self.area, circularity=self.circularity,
                    inertia_ratio=self.inertia_ratio, fill_ratio=self.fill_ratio,
                    major_axis_px=self.major_axis_px, minor_axis_px=self.minor_axis_px,
                    angle_rad=self.angle_rad)


_PAD = _RIM_PX + 1  # padding of each region's bounding box for its centre of gravity


def weighted_centres(
    image_u8: NDArray[np.uint8], regions: Sequence[Region], polarity: Polarity
) -> list[tuple[float, float] | None]:
    """Contrast-weighted centres of gravity of regions, over their padded bounding boxes.

    Each region's weights are its pixels' contrast against the mean of the ring around it
    (the padded box minus the slightly dilated region), clipped at zero, within the dilated
    region -- so the anti-aliased rim counts and the global threshold does not matter. All
    regions are done in one batch: their patches are laid side by side (with a gap, so the
    dilation cannot cross) in one strip, which costs one drawContours, one dilate and a few
    numpy reductions instead of a dozen OpenCV calls per region. Contours are in frame
    coordinates, so a region found in a tracking window gets exactly the full search's centre.
    """
    if not regions:
        return []
    h_img, w_img = image_u8.shape
    boxes = []
    for r in regions:
        x, y, w, h = r.rect
        boxes.append((max(x - _PAD, 0), max(y - _PAD, 0),
                      min(x + w + _PAD, w_img), min(y + h + _PAD, h_img)))
    height = max(y1 - y0 for _, y0, _, y1 in boxes)
    stride = max(x1 - x0 for x0, _, x1, _ in boxes) + _RIM_PX
    k = len(regions)
    pixels = np.zeros((height, k * stride), np.uint8)
    valid = np.zeros((height, k * stride), np.uint8)
    shifted = []
    for i, (r, (x0, y0, x1, y1)) in enumerate(zip(regions, boxes, strict=True)):
        left = i * stride
        pixels[: y1 - y0, left:left + x1 - x0] = image_u8[y0:y1, x0:x1]
        valid[: y1 - y0, left:left + x1 - x0] = 1
        shifted.append(r.contour + np.array([left - x0, -y0], np.int32))
    region = np.zeros(pixels.shape, np.uint8)
    cv2.drawContours(region, shifted, -1, 1, -1)
    near = cv2.dilate(region, _DILATE)
    # Mean rather than median of the surrounding ring: 10x cheaper, and a neighbour
    # intruding into the ring only scales the weights, it does not move the centre much.
    ring = cv2.subtract(valid, near)  # 1 on the padded box outside the dilated region
    pix = pixels.astype(np.float64)
    # Per-region sums as column sums of the strip folded per patch (2-D reductions only).
    ring_sum = (pix * ring).sum(axis=0).reshape(k, stride).sum(axis=1)
    ring_n = ring.sum(axis=0, dtype=np.int64).reshape(k, stride).sum(axis=1)
    background = np.repeat(ring_sum / np.maximum(ring_n, 1), stride)
    contrast = background - pix if polarity == "dark" else pix - background
    weights = np.maximum(contrast, 0.0) * near
    columns = weights.sum(axis=0).reshape(k, stride)
    m00 = columns.sum(axis=1)
    m10 = columns @ np.arange(stride, dtype=np.float64)
    m01 = np.arange(height, dtype=np.float64) @ weights.reshape(height, k, stride).sum(axis=2)
    out: list[tuple[float, float] | None] = []
    for (x0, y0, _, _), s0, sx, sy in zip(boxes, m00.tolist(), m10.tolist(), m01.tolist(),
                                          strict=True):
        out.append((x0 + sx / s0, y0 + sy / s0) if s0 > 0.0 else None)
    return out


def dot_regions(
    mask_u8: NDArray[np.uint8], filt: BlobFilter, offset: tuple[int, int] = (0, 0),
) -> list[Region]:
    """Regions of a binary mask that look like dots, in frame coordinates.

    ``mask_u8`` covers the frame window at ``offset`` = (x, y). Regions touching the window
    border are dropped: a cut dot has a biased centre. The filters run cheapest first (outline
    length, bounding box, area, then convex hull, perimeter, moments), so clutter costs little.
    """
    contours, hierarchy = cv2.findContours(
        mask_u8, cv2.RETR_CCOMP, cv2.CHAIN_APPROX_SIMPLE, offset=offset
    )
    if hierarchy is None:
        return []
    hier = hierarchy[0].tolist()
    h_img, w_img = mask_u8.shape
    ox, oy = offset
    x_end, y_end = ox + w_img, oy + h_img
    min_area, max_area = filt.min_area_px, filt.max_area_px
    out: list[Region] = []
    for i, c in enumerate(contours):
        if hier[i][3] >= 0 or len(c) < 3:  # holes are not dots; specks have no outline
            continue
        x, y, w, h = cv2.boundingRect(c)
        if w * h < min_area or x <= ox or y <= oy or x + w >= x_end or y + h >= y_end:
            continue  # a speck (the region fits in its box), or cut by the window border
        outer = cv2.contourArea(c)
        if not min_area <= outer <= 2.0 * max_area:
            continue
        area = _region_area(contours, hier, i) if hier[i][2] >= 0 else outer
        if not min_area <= area <= max_area:
            continue
        hull_area = cv2.contourArea(cv2.convexHull(c))
        fill = area / hull_area if hull_area > 0 else 0.0
        if fill < filt.min_fill_ratio:
            continue
        perimeter = cv2.arcLength(c, True)
        circularity = 4.0 * math.pi * area / (perimeter * perimeter) if perimeter > 0 else 0.0
        if circularity < filt.min_circularity:
            continue
        m = cv2.moments(c)
        if m["m00"] <= 0:
            continue
        mu20, mu02, mu11 = m["mu20"] / m["m00"], m["mu02"] / m["m00"], m["mu11"] / m["m00"]
        half_diff = math.hypot((mu20 - mu02) / 2.0, mu11)
        lam_major = (mu20 + mu02) / 2.0 + half_diff
        lam_minor = max((mu20 + mu02) / 2.0 - half_diff, 0.0)
        inertia = math.sqrt(lam_minor / lam_major) if lam_major > 0 else 0.0
        if inertia < filt.min_inertia_ratio:
            continue
        out.append(Region(
            c, (x, y, w, h), area, min(circularity, 1.0), inertia, fill,
            4.0 * math.sqrt(lam_major), 4.0 * math.sqrt(lam_minor),
            0.5 * math.atan2(2.0 * mu11, mu20 - mu02),
            (m["m10"] / m["m00"], m["m01"] / m["m00"]),
        ))
    return out


def blobs_from_regions(
    image_u8: NDArray[np.uint8], regions: Sequence[Region], polarity: Polarity
) -> list[Blob]:
    """Blobs with grey-level centres for these regions (those without contrast dropped)."""
    centres = weighted_centres(image_u8, regions, polarity)
    return [r.blob(*c) for r, c in zip(regions, centres, strict=True) if c is not None]


def blobs_from_mask(
    image_u8: NDArray[np.uint8],
    mask_u8: NDArray[np.uint8],
    polarity: Polarity,
    filt: BlobFilter,
    offset: tuple[int, int] = (0, 0),
) -> list[Blob]:
    """Dots among the regions of a binary mask of the window of ``image_u8`` at ``offset``.

    ``image_u8`` is the whole frame; ``mask_u8`` covers ``image_u8[y:y+h, x:x+w]`` with
    ``offset`` = (x, y) (see :func:`dot_regions`); only the survivors of the shape filters get
    the grey-level centre (:func:`weighted_centres`).
    """
    return blobs_from_regions(image_u8, dot_regions(mask_u8, filt, offset), polarity)


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
    the window that can hold dots (:func:`candidate_window`), and only that window is
    thresholded and traced at full resolution; ``coarse=False`` always traces the whole frame.
    """
    img = _check_image(image_u8)
    if polarity not in ("dark", "light"):
        raise ValueError(f'polarity must be "dark" or "light", got {polarity!r}')
    f = filt if filt is not None else BlobFilter()
    if threshold == "adaptive":
        return blobs_from_mask(img, adaptive_binarize(img, polarity), polarity, f), None
    sample = _subsample(img)
    thr = _otsu_of_sample(sample) if threshold is None or threshold == "otsu" else float(
        threshold)
    win = candidate_window(sample, polarity, thr, f, img.shape) if coarse else None
    if win is None:
        return blobs_from_mask(img, binarize(img, polarity, thr), polarity, f), thr
    x0, y0, x1, y1 = win
    mask = binarize(img[y0:y1, x0:x1], polarity, thr)
    return blobs_from_mask(img, mask, polarity, f, (x0, y0)), thr


def detect_blobs(
    image_u8: NDArray[np.uint8],
    polarity: Polarity = "dark",
    *,
    min_area_px: float = 12.0,
    max_area_px: float = 20000.0,
    min_circularity: float = 0.6,
    min_inertia_ratio: float = 0.3,
    min_fill_ratio: float = 0.85,
    threshold: ThresholdSpec = None,
) -> list[Blob]:
    """Dark (or light) roughly elliptical dots of the frame with sub-pixel centres.

    ``threshold``: None/"otsu" (global Otsu, the fast default), "adaptive" (local mean; for
    strongly uneven lighting) or a grey level. Lines, frames, text and specks fail the area,
    fill-ratio (region / convex hull), circularity (4*pi*A/P^2) or inertia-ratio (minor/major
    axis) filters. Raises ValueError for a non-8-bit or non-grey image.
    """
    filt = BlobFilter(min_area_px, max_area_px, min_circularity, min_inertia_ratio, min_fill_ratio)
    return detect_blobs_thresholded(image_u8, polarity, filt, threshold)[0]
