"""Dot detection on 8-bit grey frames: threshold, contours, shape filters, sub-pixel centres.

The fast path thresholds the full frame once (Otsu on a 4x-subsampled copy, which finds
nearly the same threshold for a sixteenth of the histogram work), finds region outlines with
cv2.findContours and gets area and shape from contour moments. Only the survivors get the
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


def otsu_threshold(image_u8: NDArray[np.uint8]) -> float:
    """Otsu's threshold of the frame, from every fourth pixel of every fourth row."""
    sample = np.ascontiguousarray(image_u8[::4, ::4])
    thr, _ = cv2.threshold(sample, 0, 255, cv2.THRESH_BINARY | cv2.THRESH_OTSU)
    return float(thr)


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


def _weighted_centre(
    image_u8: NDArray[np.uint8], contour: Contour, rect: tuple[int, int, int, int],
    polarity: Polarity,
) -> tuple[float, float] | None:
    """Contrast-weighted centre of gravity over the padded bounding box of one region.

    ``contour`` and ``rect`` (its bounding box) are in frame coordinates, so a region found in
    a tracking window gets exactly the centre the full search gives it. OpenCV calls only: at
    this patch size (~20x20 px) each numpy call would cost as much as the arithmetic.
    """
    h_img, w_img = image_u8.shape
    x, y, w, h = rect
    x0, y0 = max(x - _RIM_PX - 1, 0), max(y - _RIM_PX - 1, 0)
    x1, y1 = min(x + w + _RIM_PX + 1, w_img), min(y + h + _RIM_PX + 1, h_img)
    window = image_u8[y0:y1, x0:x1]
    region = np.zeros(window.shape, np.uint8)
    cv2.drawContours(region, [contour], 0, 255, -1, offset=(-x0, -y0))
    near = cv2.dilate(region, _DILATE)
    # Mean rather than median of the surrounding ring: 10x cheaper, and a neighbour
    # intruding into the ring only scales the weights, it does not move the centre much.
    background = cv2.mean(window, mask=cv2.bitwise_not(near))[0]
    weights = np.zeros(window.shape, np.float32)
    if polarity == "dark":  # contrast against the background, only near the region
        cv2.subtract((background, 0.0, 0.0, 0.0), window, weights, near, cv2.CV_32F)  # type: ignore[call-overload]
    else:
        cv2.subtract(window, (background, 0.0, 0.0, 0.0), weights, near, cv2.CV_32F)  # type: ignore[call-overload]
    cv2.threshold(weights, 0.0, 0.0, cv2.THRESH_TOZERO, weights)  # negative contrast: no weight
    m = cv2.moments(weights)
    if m["m00"] <= 0.0:
        return None
    return x0 + m["m10"] / m["m00"], y0 + m["m01"] / m["m00"]


def blobs_from_mask(
    image_u8: NDArray[np.uint8],
    mask_u8: NDArray[np.uint8],
    polarity: Polarity,
    filt: BlobFilter,
    offset: tuple[int, int] = (0, 0),
) -> list[Blob]:
    """Dots among the regions of a binary mask of the window of ``image_u8`` at ``offset``.

    ``image_u8`` is the whole frame; ``mask_u8`` covers ``image_u8[y:y+h, x:x+w]`` with
    ``offset`` = (x, y), so a tracking window reports frame coordinates and the same centres
    as the full search. Regions touching the window border are dropped: a cut dot has a
    biased centre. The filters run cheapest first (outline length, area, bounding box, then
    convex hull, perimeter, moments), so clutter costs little Python work.
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
    out: list[Blob] = []
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
        centre = _weighted_centre(image_u8, c, (x, y, w, h), polarity)
        if centre is None:
            continue
        out.append(Blob(
            u=centre[0], v=centre[1], area=area,
            circularity=min(circularity, 1.0), inertia_ratio=inertia, fill_ratio=fill,
            major_axis_px=4.0 * math.sqrt(lam_major), minor_axis_px=4.0 * math.sqrt(lam_minor),
            angle_rad=0.5 * math.atan2(2.0 * mu11, mu20 - mu02),
        ))
    return out


def detect_blobs_thresholded(
    image_u8: NDArray[np.uint8],
    polarity: Polarity = "dark",
    filt: BlobFilter | None = None,
    threshold: ThresholdSpec = None,
) -> tuple[list[Blob], float | None]:
    """:func:`detect_blobs` that also returns the global threshold it used (None if adaptive),
    so the tracker can reuse it in its windows and find the very same regions."""
    img = _check_image(image_u8)
    if polarity not in ("dark", "light"):
        raise ValueError(f'polarity must be "dark" or "light", got {polarity!r}')
    f = filt if filt is not None else BlobFilter()
    if threshold == "adaptive":
        return blobs_from_mask(img, adaptive_binarize(img, polarity), polarity, f), None
    thr = otsu_threshold(img) if threshold is None or threshold == "otsu" else float(threshold)
    return blobs_from_mask(img, binarize(img, polarity, thr), polarity, f), thr


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
