"""The dot target: 3-D dot centres in the target frame (mm), dot size and polarity."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import numpy as np
from numpy.typing import ArrayLike, NDArray

Polarity = Literal["dark", "light"]
MIN_DOTS, MAX_DOTS = 4, 100
MAX_COORDINATE_MM = 10_000.0  # a dot 10 m from the target's origin is a typo, not a target
_DISTINCT_FRACTION = 1e-6  # dots closer than this fraction of the layout's size coincide


def layout_problem(points_mm: ArrayLike) -> str | None:
    """Why a dot layout cannot determine a pose (None when it can).

    A pose needs 4 or more distinct dots that are not all on one line: three collinear dots
    and a fourth off their line (or any 4 in general position) fix all six degrees of
    freedom, a line of dots leaves the rotation about it free. Used by :class:`Target` and by
    configuration loaders, so a bad model is refused before any frame is seen.
    """
    pts = np.asarray(points_mm, dtype=float)
    if pts.ndim != 2 or pts.shape[1] != 3:
        return f"points_mm must be a list of [x, y, z], got shape {pts.shape}"
    if not np.all(np.isfinite(pts)):
        return "points_mm must be finite numbers"
    if pts.size and float(np.abs(pts).max()) > MAX_COORDINATE_MM:
        # also keeps the spans and the SVD below finite (1e308 - -1e308 overflows)
        return (f"points_mm must be within +-{MAX_COORDINATE_MM:g} mm of the target's origin, "
                f"got {float(np.abs(pts).max()):g}")
    if not MIN_DOTS <= len(pts) <= MAX_DOTS:
        return f"a target has {MIN_DOTS} to {MAX_DOTS} dots, got {len(pts)}"
    extent = float(np.ptp(pts, axis=0).max())
    tol = _DISTINCT_FRACTION * max(extent, 1e-9)
    distinct: list[NDArray[np.float64]] = []
    for p in pts:
        if all(float(np.linalg.norm(p - q)) > tol for q in distinct):
            distinct.append(p)
    if len(distinct) < MIN_DOTS:
        return (f"the dots have only {len(distinct)} distinct positions: a pose needs "
                f"{MIN_DOTS} or more different dots")
    centred = np.asarray(distinct) - np.mean(distinct, axis=0)
    s = np.linalg.svd(centred, compute_uv=False)
    if s[1] <= 1e-6 * s[0]:
        return ("all dots lie on one line: the rotation about that line cannot be "
                "determined; put at least one dot off the line")
    return None


@dataclass(frozen=True, eq=False)
class Target:
    """A rigid set of 4 to 100 circular dots that determines a pose (see
    :func:`layout_problem`): any layout, including circle grids and collinear subsets.

    ``points_mm`` are the dot centres in the target frame. Planar targets lie in z = 0 of that
    frame by convention, with +z pointing away from the camera side (into the plate).
    ``polarity`` says whether the dots are darker ("dark") or brighter ("light") than the plate.
    """

    points_mm: NDArray[np.float64]
    dot_diameter_mm: float
    polarity: Polarity = "dark"

    def __init__(
        self, points_mm: ArrayLike, dot_diameter_mm: float, polarity: Polarity = "dark"
    ) -> None:
        pts = np.array(points_mm, dtype=float)
        problem = layout_problem(pts)
        if problem is not None:
            raise ValueError(problem)
        if not dot_diameter_mm > 0:
            raise ValueError(f"dot_diameter_mm must be positive, got {dot_diameter_mm}")
        if polarity not in ("dark", "light"):
            raise ValueError(f'polarity must be "dark" or "light", got {polarity!r}')
        pts.setflags(write=False)
        object.__setattr__(self, "points_mm", pts)
        object.__setattr__(self, "dot_diameter_mm", float(dot_diameter_mm))
        object.__setattr__(self, "polarity", polarity)

    @property
    def n_points(self) -> int:
        return len(self.points_mm)

    @property
    def is_planar(self) -> bool:
        """True when all dots lie (within 1e-6 of the target's extent) on one plane."""
        centred = self.points_mm - self.points_mm.mean(axis=0)
        s = np.linalg.svd(centred, compute_uv=False)
        return bool(s[2] <= 1e-6 * max(s[0], 1e-12))
