"""The dot target: 3-D dot centres in the target frame (mm), dot size and polarity."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import numpy as np
from numpy.typing import ArrayLike, NDArray

Polarity = Literal["dark", "light"]


@dataclass(frozen=True, eq=False)
class Target:
    """A rigid set of 4 to 12 circular dots.

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
        pts = np.asarray(points_mm, dtype=float)
        if pts.ndim != 2 or pts.shape[1] != 3:
            raise ValueError(f"points_mm must be a list of [x, y, z], got shape {pts.shape}")
        if not 4 <= len(pts) <= 12:
            raise ValueError(f"a target has 4 to 12 dots, got {len(pts)}")
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
