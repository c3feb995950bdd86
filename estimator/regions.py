"""Compiled kernels of dot detection: region labelling in regions of interest, shape, centres.

Detection is per-pixel and per-region loops over a few thousand to a few tens of thousands of
pixels, which Python and even per-region OpenCV calls spend most of their time dispatching.
These kernels run compiled (numba, cached on disk after the first use) and take plain arrays, so
a frame costs one or two calls from :mod:`estimator.blobs`.

Conventions shared with :mod:`estimator.blobs`:

- A pixel is dot when ``pixel <= threshold`` (dark dots) or ``pixel > threshold`` (light), as
  OpenCV's THRESH_BINARY_INV / THRESH_BINARY would make it; with a mask, when ``mask != 0``.
- Regions are 8-connected. A region is only measured inside its region of interest (ROI); one
  that touches the ROI's border is dropped, because a cut dot has a biased centre. ROIs may
  overlap: a region wholly inside two of them is reported once (the same first pixel).
- Shape: ``area`` is the area enclosed by the outline through the boundary pixels' centres,
  as OpenCV's contour area measures it (from the pixel count and the boundary count by Pick's
  theorem), so area limits mean what they mean for OpenCV's blob detector; ``fill_ratio`` is
  that area over the area of the convex hull of the pixel centres (holes, notches and text
  strokes lower it); ``circularity`` is 4 pi area / P^2 with P the perimeter of that hull (a
  disc gives ~1, a square pi/4, a line of width w and length L about pi w / L: concave shapes
  are left to the fill ratio); ``inertia_ratio`` is sqrt(lambda_min / lambda_max) of the
  second moments of the pixel squares (binary moments plus 1/12 per axis).
- Ellipse fit: a circular dot seen at a tilt images as an ellipse, so dots are judged by how
  well the region matches the ellipse of its own second moments (a filled ellipse with
  covariance S has the boundary x^T S^-1 x = 4), not by circularity, which falls with the
  tilt. ``ellipse_error`` is the rms radial distance (px) of the region's outline -- the ends of
  each row's extent and the middle of the top and bottom rows, at pixel edges -- from that
  ellipse, over the ellipse's mean semi-axis plus ``ELLIPSE_SLACK_PX`` (the pixel grid alone
  leaves ~0.3 px rms): ~0.02-0.07 for an ellipse of any size and tilt, 0.1-0.15 for squares and
  triangles, more for anything ragged. The tilt itself is limited by the inertia ratio
  (cos(tilt) for an ellipse).
- The centre of a surviving region is the grey-level weighted centre of gravity over its
  bounding box padded by ``PAD_PX``: weights are each pixel's contrast against the background
  (the mean grey level of the padded box outside the region -- filled row by row -- dilated by
  ``RIM_PX``) over the dot's contrast (the mean level of the region's core, less its outline
  pixels, against that background), clipped to [0, 1], inside the dilated region: a coverage,
  so shading across a dot pulls its centre less. The anti-aliased rim counts and the
  global threshold does not matter; pixel centres sit at integer coordinates. Every weight
  then loses ``WEIGHT_FLOOR`` and counts only above zero (a thresholded centre of gravity):
  the background pixels of the dilated rim carry no dot, only noise, at the largest lever
  from the centre, and they gave a third of a centre's noise variance. Without them their
  noise moves no centre, one frame's view is ~20 % less noisy, and rendered dots
  lie nearer their analytic centre (docs/estimator.md); a pixel enters with weight zero as
  the dot moves, so the pull towards the pixel grid does not grow.
"""

from __future__ import annotations

import math

import numba
import numpy as np
from numpy.typing import NDArray

RIM_PX = 2  # the blurred rim beyond the thresholded region that still carries weight
PAD_PX = RIM_PX + 1  # padding of a region's bounding box for its centre of gravity
# share of the dot's contrast taken off every weight: several times a background pixel's
# noise (~0.01 of the contrast in the simulated camera), a small part of a rim pixel's weight
WEIGHT_FLOOR = 0.05
# Columns of the per-dot result rows (see find_dots). MID_LEVEL is the grey level halfway
# between the dot's core and its background: where its own edge is, whatever the threshold.
(U, V, AREA, CIRCULARITY, INERTIA, FILL, MAJOR, MINOR, ANGLE, ELLIPSE, MASK_U, MASK_V,
 MID_LEVEL) = range(13)
N_COLUMNS = 13
ELLIPSE_SLACK_PX = 2.0  # added to the mean semi-axis when normalising the ellipse error


@numba.njit(cache=True, nogil=True)
def _radial_residual(dx: float, dy: float, i20: float, i02: float, i11: float) -> float:
    """Distance (px, signed) of the point (dx, dy) from the centre-based ellipse whose
    inverse covariance is (i20, i11; i11, i02), along the ray from its centre."""
    q = 0.25 * (i20 * dx * dx + 2.0 * i11 * dx * dy + i02 * dy * dy)
    r = math.hypot(dx, dy)
    if q <= 0.0 or r == 0.0:
        return 0.0
    return r * (1.0 - 1.0 / math.sqrt(q))


@numba.njit(cache=True, nogil=True)
def _ellipse_error(
    row_min: NDArray[np.int64], row_max: NDArray[np.int64], by0: int, by1: int,
    sx: int, sy: int, mx: float, my: float, mu20: float, mu02: float, mu11: float, lam_major: float,
    lam_minor: float,
) -> float:
    """The region's ellipse error (see the module docstring): rms radial residual of the
    outline points from the moment ellipse, normalised by its mean semi-axis plus slack.
    Coordinates are taken from the region's first pixel (sx, sy; the centroid is at mx, my
    from it), so a region gets the same number in any ROI."""
    det = mu20 * mu02 - mu11 * mu11
    if det <= 0.0:
        return math.inf
    i20, i02, i11 = mu02 / det, mu20 / det, -mu11 / det
    ss = 0.0
    n = 0
    for k in range(by0, by1 + 1):
        if row_max[k] < 0:
            continue
        dy = float(k - sy) - my
        e = _radial_residual(float(row_min[k] - sx) - 0.5 - mx, dy, i20, i02, i11)
        ss += e * e
        e = _radial_residual(float(row_max[k] - sx) + 0.5 - mx, dy, i20, i02, i11)
        ss += e * e
        n += 2
    for k, dy in ((by0, float(by0 - sy) - 0.5 - my), (by1, float(by1 - sy) + 0.5 - my)):
        e = _radial_residual(0.5 * float(row_min[k] + row_max[k] - 2 * sx) - mx, dy, i20, i02,
                             i11)
        ss += e * e
        n += 1
    mean_semi_axis = 2.0 * math.sqrt(math.sqrt(lam_major * lam_minor))
    return math.sqrt(ss / n) / (mean_semi_axis + ELLIPSE_SLACK_PX)


@numba.njit(cache=True, nogil=True)
def otsu_threshold(image: NDArray[np.uint8], step: int) -> float:
    """Otsu's threshold of every ``step``-th pixel of every ``step``-th row: the grey level t
    maximising the between-class variance of [0, t] and (t, 255] (OpenCV's convention)."""
    hist = np.zeros(256, np.int64)
    for y in range(0, image.shape[0], step):
        row = image[y]
        for x in range(0, image.shape[1], step):
            hist[row[x]] += 1
    total = 0
    weighted = 0.0
    for g in range(256):
        total += hist[g]
        weighted += g * hist[g]
    best_t, best_var = 0, -1.0
    n0, sum0 = 0, 0.0
    for t in range(256):
        n0 += hist[t]
        sum0 += t * hist[t]
        n1 = total - n0
        if n0 == 0 or n1 == 0:
            continue
        m0, m1 = sum0 / n0, (weighted - sum0) / n1
        var = float(n0) * float(n1) * (m0 - m1) * (m0 - m1)
        if var > best_var:
            best_t, best_var = t, var
    return float(best_t)


@numba.njit(cache=True, nogil=True)
def _hull_area_perimeter(px: NDArray[np.float64], py: NDArray[np.float64],
                         n: int) -> tuple[float, float]:
    """Area and perimeter of the convex hull of n points (Andrew's monotone chain)."""
    order = np.argsort(px[:n] * 1e6 + py[:n])
    hull_x = np.empty(2 * n + 1)
    hull_y = np.empty(2 * n + 1)
    k = 0
    for rep in range(2):  # lower chain left to right, then upper chain right to left
        start = k
        for idx in range(n):
            i = order[idx] if rep == 0 else order[n - 1 - idx]
            x, y = px[i], py[i]
            while k >= start + 2:
                ax, ay = hull_x[k - 2], hull_y[k - 2]
                bx, by = hull_x[k - 1], hull_y[k - 1]
                if (bx - ax) * (y - ay) - (by - ay) * (x - ax) > 0.0:
                    break
                k -= 1
            hull_x[k], hull_y[k] = x, y
            k += 1
        k -= 1  # the chain's last point starts the other chain
    area2 = 0.0
    perimeter = 0.0
    for i in range(k):
        j = (i + 1) % k
        area2 += hull_x[i] * hull_y[j] - hull_x[j] * hull_y[i]
        perimeter += math.hypot(hull_x[j] - hull_x[i], hull_y[j] - hull_y[i])
    return abs(area2) / 2.0, perimeter


@numba.njit(cache=True, nogil=True)
def _weighted_centre(
    image: NDArray[np.uint8], row_min: NDArray[np.int64], row_max: NDArray[np.int64],
    rx0: int, ry0: int, by0: int, by1: int, dark: bool,
) -> tuple[float, float, bool, float]:
    """Contrast-weighted centre of a region (see the module docstring) -> (u, v, ok,
    mid_level): mid_level is halfway between the region's core level and its background.

    The region is given by its extent on each of its rows (``row_min``/``row_max``, ROI
    coordinates, rows by0..by1, ROI at rx0, ry0), i.e. filled row by row like a filled
    outline; its dilation by RIM_PX (a square) is then, row by row, the union of the extents
    of the rows within RIM_PX, widened by RIM_PX -- no per-pixel dilation needed. The box is
    the bounding box padded by PAD_PX, clipped to the frame.
    """
    height, width = image.shape
    fy0, fy1 = max(ry0 + by0 - PAD_PX, 0), min(ry0 + by1 + PAD_PX, height - 1)
    x_lo, x_hi = width, -1
    for k in range(by0, by1 + 1):
        if row_max[k] >= 0:
            x_lo, x_hi = min(x_lo, row_min[k]), max(x_hi, row_max[k])
    fx0, fx1 = max(rx0 + x_lo - PAD_PX, 0), min(rx0 + x_hi + PAD_PX, width - 1)
    ring_sum = 0.0
    ring_n = 0
    near_lo = np.empty(fy1 - fy0 + 1, np.int64)
    near_hi = np.empty(fy1 - fy0 + 1, np.int64)
    for y in range(fy0, fy1 + 1):
        lo, hi = width, -1
        for k in range(max(y - ry0 - RIM_PX, by0), min(y - ry0 + RIM_PX, by1) + 1):
            if row_max[k] >= 0:
                lo, hi = min(lo, row_min[k]), max(hi, row_max[k])
        if hi >= 0:
            lo, hi = max(rx0 + lo - RIM_PX, fx0), min(rx0 + hi + RIM_PX, fx1)
        else:
            lo, hi = fx1 + 1, fx1  # no near pixel on this row
        near_lo[y - fy0], near_hi[y - fy0] = lo, hi
        row = image[y]
        for x in range(fx0, lo):
            ring_sum += row[x]
        for x in range(hi + 1, fx1 + 1):
            ring_sum += row[x]
        ring_n += (lo - fx0) + (fx1 - hi)
    background = ring_sum / max(ring_n, 1)
    # The dot's own level: the mean over its core (the region less its outline pixels, whose
    # anti-aliasing makes them paler). Contrast is scaled by it and capped at 1, so the core
    # weighs evenly -- shading across a dot pulls its centre less -- and the rim pixels by
    # their coverage.
    inner_sum = 0.0
    inner_n = 0
    for k in range(by0 + 1, by1):  # the core: one pixel in from the region's outline
        if row_max[k] >= 0:
            lo = max(row_min[k], row_min[k - 1], row_min[k + 1]) + 1  # rows of a connected
            # region between its first and last are never empty
            hi = min(row_max[k], row_max[k - 1], row_max[k + 1]) - 1
            row = image[ry0 + k]
            for x in range(rx0 + lo, rx0 + hi + 1):
                inner_sum += row[x]
            inner_n += max(hi - lo + 1, 0)
    if inner_n == 0:  # too small for a core: the whole region
        for k in range(by0, by1 + 1):
            if row_max[k] >= 0:
                row = image[ry0 + k]
                for x in range(rx0 + row_min[k], rx0 + row_max[k] + 1):
                    inner_sum += row[x]
                inner_n += row_max[k] - row_min[k] + 1
    full = (background - inner_sum / max(inner_n, 1) if dark
            else inner_sum / max(inner_n, 1) - background)
    mid_level = background - 0.5 * full if dark else background + 0.5 * full
    if full <= 0.0:
        return 0.0, 0.0, False, mid_level
    s0 = sx = sy = 0.0
    for y in range(fy0, fy1 + 1):
        row = image[y]
        for x in range(near_lo[y - fy0], near_hi[y - fy0] + 1):
            g = float(row[x])
            c = min((background - g if dark else g - background) / full, 1.0) - WEIGHT_FLOOR
            if c > 0.0:
                s0 += c
                sx += c * x
                sy += c * y
    if s0 <= 0.0:
        return 0.0, 0.0, False, mid_level
    return sx / s0, sy / s0, True, mid_level


@numba.njit(cache=True, nogil=True)
def find_dots(
    image: NDArray[np.uint8], mask: NDArray[np.uint8], use_mask: bool, threshold: float,
    dark: bool, rois: NDArray[np.int64], min_area_px: float, max_area_px: float,
    min_circularity: float, min_inertia_ratio: float, min_fill_ratio: float,
    max_ellipse_error: float,
) -> NDArray[np.float64]:
    """Dots in the ROIs (K,4: x0, y0, x1, y1, end exclusive; may overlap) -> rows of
    N_COLUMNS (U, V, AREA, ... MASK_V: see the column names), in the frame's scan order of their
    first pixels (the order a pass over the whole frame finds them in).

    Each ROI is thresholded into a label buffer with a one-pixel background border (so the
    flood fill needs no bounds checks), then labelled. Regions touching their ROI's border,
    outside [min_area_px, max_area_px] or below a shape limit are skipped; the survivors get
    their weighted centre. Cheap tests come first (the area is known when the flood fill
    ends, the hull only for plausible sizes), so clutter costs little.
    """
    width = image.shape[1]
    max_h = max_w = 1
    for r in range(rois.shape[0]):
        max_h = max(max_h, rois[r, 3] - rois[r, 1])
        max_w = max(max_w, rois[r, 2] - rois[r, 0])
    level = np.int32(max(min(math.floor(threshold), 256), -1))  # g <= t iff g <= floor(t)
    cls = np.empty((max_h + 2) * (max_w + 2), np.int32)  # 0 background, -1 dot, k > 0 label k
    stack = np.empty(max_h * max_w, np.int64)
    pending = np.empty(max_h, np.int64)
    row_min = np.empty(max_h, np.int64)  # extent of the current region on each ROI row

    row_max = np.empty(max_h, np.int64)
    hull_x = np.empty(2 * max_h)
    hull_y = np.empty(2 * max_h)
    out = np.empty((16, N_COLUMNS))
    first = np.empty(16, np.int64)  # frame index of each dot's first pixel in scan order
    n_out = 0
    for r in range(rois.shape[0]):
        x0, y0, x1, y1 = rois[r, 0], rois[r, 1], rois[r, 2], rois[r, 3]
        h, w = y1 - y0, x1 - x0
        if h <= 2 or w <= 2:
            continue
        stride = w + 2
        cls[:stride] = 0  # the border rows; every other pixel is written below
        cls[(h + 1) * stride:(h + 2) * stride] = 0
        for y in range(h):
            base = (y + 1) * stride + 1
            cls[base - 1] = 0
            cls[base + w] = 0
            n_dot = np.int32(0)
            if use_mask:
                mrow = mask[y0 + y, x0:x1]
                for x in range(w):
                    is_dot = np.int32(mrow[x] != 0)
                    cls[base + x] = -is_dot
                    n_dot += is_dot
            elif dark:
                irow = image[y0 + y, x0:x1]
                for x in range(w):
                    is_dot = np.int32(np.int32(irow[x]) <= level)
                    cls[base + x] = -is_dot
                    n_dot += is_dot
            else:
                irow = image[y0 + y, x0:x1]
                for x in range(w):
                    is_dot = np.int32(np.int32(irow[x]) > level)
                    cls[base + x] = -is_dot
                    n_dot += is_dot
            pending[y] = n_dot  # dot pixels of the row not labelled yet
            row_min[y] = w
            row_max[y] = -1
        label = 0
        used0, used1 = 0, -1  # rows whose extents the last region set (reset before the next)
        for sy in range(h):
            if pending[sy] == 0:
                continue  # most rows of a window hold no (unlabelled) dot pixel
            for sx in range(w):
                start = (sy + 1) * stride + sx + 1
                if cls[start] != -1:
                    continue
                label += 1
                cls[start] = label
                pending[sy] -= 1
                for k in range(used0, used1 + 1):
                    row_min[k] = w
                    row_max[k] = -1
                top = 0
                stack[top] = start
                top += 1
                count = 0
                boundary = 0  # pixels with a 4-neighbour outside the region
                m10 = m01 = m20 = m02 = m11 = 0.0
                bx0, by0, bx1, by1 = sx, sy, sx, sy
                touches = False
                while top > 0:
                    top -= 1
                    i = stack[top]
                    cy, cx = i // stride - 1, i % stride - 1
                    count += 1
                    fx, fy = float(cx - sx), float(cy - sy)  # from the first pixel: the same
                    # numbers whatever the ROI, so a region gets the same shape in any ROI
                    m10 += fx
                    m01 += fy
                    m20 += fx * fx
                    m02 += fy * fy
                    m11 += fx * fy
                    bx0, by0, bx1, by1 = min(bx0, cx), min(by0, cy), max(bx1, cx), max(by1, cy)
                    row_min[cy] = min(row_min[cy], cx)
                    row_max[cy] = max(row_max[cy], cx)
                    if cx == 0 or cy == 0 or cx == w - 1 or cy == h - 1:
                        touches = True  # the region may go on beyond the ROI
                    if (cls[i - 1] == 0 or cls[i + 1] == 0 or cls[i - stride] == 0
                            or cls[i + stride] == 0):
                        boundary += 1
                    for j in (i - stride - 1, i - stride, i - stride + 1, i - 1, i + 1,
                              i + stride - 1, i + stride, i + stride + 1):
                        if cls[j] == -1:
                            cls[j] = label
                            pending[j // stride - 1] -= 1
                            stack[top] = j
                            top += 1
                used0, used1 = by0, by1
                # The area enclosed by the outline through the boundary pixels' centres (Pick:
                # A = I + B/2 - 1 with count = I + B), as OpenCV's contour area measures it.
                area = count - 0.5 * boundary - 1.0
                if touches or area < min_area_px or area > max_area_px:
                    continue
                mx, my = m10 / count, m01 / count  # relative to the first pixel
                mu20 = m20 / count - mx * mx + 1.0 / 12.0
                mu02 = m02 / count - my * my + 1.0 / 12.0
                mu11 = m11 / count - mx * my
                half_diff = math.hypot((mu20 - mu02) / 2.0, mu11)
                lam_major = (mu20 + mu02) / 2.0 + half_diff
                lam_minor = max((mu20 + mu02) / 2.0 - half_diff, 0.0)
                inertia = math.sqrt(lam_minor / lam_major) if lam_major > 0.0 else 0.0
                if inertia < min_inertia_ratio:
                    continue
                n_pts = 0
                for k in range(by0, by1 + 1):
                    if row_max[k] < 0:
                        continue
                    hull_x[n_pts], hull_y[n_pts] = row_min[k], k
                    hull_x[n_pts + 1], hull_y[n_pts + 1] = row_max[k], k
                    n_pts += 2
                hull_area, perimeter = _hull_area_perimeter(hull_x, hull_y, n_pts)
                fill = area / hull_area if hull_area > 0.0 else 0.0
                if fill < min_fill_ratio:
                    continue
                circularity = (4.0 * math.pi * area / (perimeter * perimeter)
                               if perimeter > 0.0 else 0.0)
                if circularity < min_circularity:
                    continue
                ellipse_err = _ellipse_error(row_min, row_max, by0, by1, sx, sy, mx, my,
                                             mu20, mu02, mu11, lam_major, lam_minor)
                if ellipse_err > max_ellipse_error:
                    continue
                u, v, ok, mid = _weighted_centre(image, row_min, row_max, x0, y0, by0, by1,
                                                 dark)
                if not ok:
                    continue
                first_px = (y0 + sy) * width + (x0 + sx)
                seen = False
                for k in range(n_out):
                    seen = seen or first[k] == first_px
                if seen:
                    continue  # the same region, whole in an overlapping ROI too
                if n_out == out.shape[0]:
                    grown = np.empty((2 * n_out, N_COLUMNS))
                    grown[:n_out] = out
                    out = grown
                    grown_first = np.empty(2 * n_out, np.int64)
                    grown_first[:n_out] = first
                    first = grown_first
                first[n_out] = first_px
                row = out[n_out]
                row[U], row[V], row[AREA] = u, v, area
                row[CIRCULARITY], row[INERTIA], row[FILL] = min(circularity, 1.0), inertia, fill
                row[MAJOR], row[MINOR] = 4.0 * math.sqrt(lam_major), 4.0 * math.sqrt(lam_minor)
                row[ANGLE] = 0.5 * math.atan2(2.0 * mu11, mu20 - mu02)
                row[ELLIPSE] = ellipse_err
                row[MASK_U], row[MASK_V] = (x0 + sx) + mx, (y0 + sy) + my
                row[MID_LEVEL] = mid
                n_out += 1
    return out[np.argsort(first[:n_out], kind="mergesort")]
