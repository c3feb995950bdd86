"""What can go wrong with a commissioned cell while it runs: the faults the simulated world can
be given, as deltas on its commissioned truth.

A camera knocked on its bracket (``T_mount_delta``: the true mount becomes ``T_mount0 @
delta``, on the flange or, for a fixed camera, in the base frame), a lens that refocused or
whose optics shifted (``focal_scale`` on fx and fy, ``principal_point_delta_px`` on cx, cy), a
fixed reference plate knocked (``T_reference_delta``) and a part slipped without the cell
knowing (``T_slip`` of part ``slip_part``). Each is absent at its neutral value; the world
keeps its commissioned truth apart, so clearing a fault restores it exactly.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Protocol

import numpy as np
from numpy.typing import NDArray

from estimator import CameraModel

Matrix4 = NDArray[np.float64]


class FaultSet(Protocol):
    """The faults to set, each at its neutral value when absent (None, 1, zero)."""

    @property
    def T_mount_delta(self) -> Matrix4 | None: ...

    @property
    def focal_scale(self) -> float: ...

    @property
    def principal_point_delta_px(self) -> tuple[float, float]: ...

    @property
    def T_reference_delta(self) -> Matrix4 | None: ...

    @property
    def slip_part(self) -> int: ...

    @property
    def T_slip(self) -> Matrix4 | None: ...


@dataclass(frozen=True, eq=False)
class Faults:
    """A :class:`FaultSet` in plain values; ``Faults()`` is none."""

    T_mount_delta: Matrix4 | None = None
    focal_scale: float = 1.0
    principal_point_delta_px: tuple[float, float] = (0.0, 0.0)
    T_reference_delta: Matrix4 | None = None
    slip_part: int = 0
    T_slip: Matrix4 | None = None

    @staticmethod
    def of(faults: FaultSet) -> Faults:
        """A copy of ``faults`` that no one else holds."""
        def copy(T: Matrix4 | None) -> Matrix4 | None:
            return None if T is None else np.array(T, dtype=float)

        dx, dy = faults.principal_point_delta_px
        return Faults(copy(faults.T_mount_delta), float(faults.focal_scale),
                      (float(dx), float(dy)), copy(faults.T_reference_delta),
                      int(faults.slip_part), copy(faults.T_slip))

    @property
    def lens_changed(self) -> bool:
        return self.focal_scale != 1.0 or any(self.principal_point_delta_px)

    def without_slip(self) -> Faults:
        return dataclasses.replace(self, slip_part=0, T_slip=None)


def faulted_lens(lens: CameraModel, faults: FaultSet) -> CameraModel:
    """``lens`` with its focal length scaled and its principal point moved by ``faults``; the
    distortion and the image size stay."""
    if not faults.focal_scale > 0.0:
        raise ValueError(f"focal_scale must be positive, got {faults.focal_scale}")
    dx, dy = faults.principal_point_delta_px
    return CameraModel(lens.fx * faults.focal_scale, lens.fy * faults.focal_scale,
                       lens.cx + dx, lens.cy + dy, tuple(lens.dist), lens.width, lens.height)


def faulted_mount(T_mount0: Matrix4, faults: FaultSet) -> Matrix4:
    """The commissioned mount with the knock composed on it: ``T_mount0 @ T_mount_delta``."""
    if faults.T_mount_delta is None:
        return np.array(T_mount0, dtype=float)
    return np.asarray(T_mount0 @ faults.T_mount_delta, dtype=float)
