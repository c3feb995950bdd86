"""Which blobs may belong to one part: groups by image distance, measured in imaged dot sizes.

Within one part every dot has another dot of the same part no farther away than the longest
edge of the layout's minimum spanning tree (its *link span*). In the image that distance
scales with the dot's imaged size, which each blob measures itself (its major axis, which a
tilt does not shorten), so two blobs are linked when they are closer than the link span in
dot diameters times the mean of their major axes (with a margin for perspective and blob-size
noise); a group is a connected set of linked blobs. Parts that lie apart fall into separate
groups whatever their distance from the camera; parts that touch or overlap in the image fall
into one group, which :func:`split_group` divides by position into the number of parts its
size suggests.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
from numpy.typing import NDArray
from scipy.sparse import csr_matrix
from scipy.sparse.csgraph import connected_components, minimum_spanning_tree

from estimator.target import Target

LINK_MARGIN = 1.3  # perspective within a part, and a dot's imaged size measured a bit small
_SPLIT_ITERATIONS = 20


def link_span_mm(target: Target) -> float:
    """The longest edge of the minimum spanning tree of the layout's dots (mm)."""
    pts = target.points_mm
    d = np.linalg.norm(pts[:, None] - pts[None], axis=2)
    tree = minimum_spanning_tree(csr_matrix(d))
    return float(tree.data.max()) if tree.nnz else 0.0


def link_span_dots(targets: Sequence[Target]) -> float:
    """The largest link span among the layouts, in dot diameters, with the margin."""
    return LINK_MARGIN * max(link_span_mm(t) / t.dot_diameter_mm for t in targets)


def group_blobs(centres_px: NDArray[np.float64], major_axes_px: NDArray[np.float64],
                span_dots: float) -> list[NDArray[np.intp]]:
    """Connected groups of blobs (indices, ascending), largest first: blobs i and j are
    linked when closer than ``span_dots`` times their mean major axis."""
    n = len(centres_px)
    if n == 0:
        return []
    d = np.linalg.norm(centres_px[:, None] - centres_px[None], axis=2)
    reach = span_dots * 0.5 * (major_axes_px[:, None] + major_axes_px[None])
    n_groups, label = connected_components(csr_matrix(d < reach), directed=False)
    groups = [np.flatnonzero(label == g).astype(np.intp) for g in range(n_groups)]
    return sorted(groups, key=lambda g: (-len(g), int(g[0])))


def split_group(centres_px: NDArray[np.float64], k: int) -> list[NDArray[np.intp]]:
    """``k`` parts of a group by position (k-means, seeded by farthest points so the split
    is the same every time), the empty ones left out."""
    n = len(centres_px)
    if k <= 1 or n <= k:
        return [np.arange(n, dtype=np.intp)]
    seeds = [int(np.argmin(centres_px[:, 0]))]
    dist = np.linalg.norm(centres_px - centres_px[seeds[0]], axis=1)
    while len(seeds) < k:
        seeds.append(int(dist.argmax()))
        dist = np.minimum(dist, np.linalg.norm(centres_px - centres_px[seeds[-1]], axis=1))
    centres = centres_px[seeds].copy()
    label = np.zeros(n, dtype=np.intp)
    for _ in range(_SPLIT_ITERATIONS):
        d = np.linalg.norm(centres_px[:, None] - centres[None], axis=2)
        new = d.argmin(axis=1)
        if np.array_equal(new, label) and _ > 0:
            break
        label = new
        for c in range(k):
            if np.any(label == c):
                centres[c] = centres_px[label == c].mean(axis=0)
    return [np.flatnonzero(label == c).astype(np.intp) for c in range(k) if np.any(label == c)]
