"""The simulated world's own truth, resolved from ``[sim]`` and its ``world`` preset.

A simulator that renders with the cell's own intrinsics and mounts the camera where
``[hand_eye]`` says cannot show a calibration error: every accuracy figure measured in it is
the estimator's alone. This module decides what the simulated lens and mount really are, apart
from what the cell believes (``[camera]``, ``[hand_eye]``), so commissioning has something to
recover and benchmarks something to miss.

``world = "ideal"``: the truth is the cell's config (the estimator's own error only).
``world = "realistic"``: the truth differs from the config by typical commissioning-day amounts
(see :data:`REALISTIC` and docs/simulator.md for where each value comes from). Explicit
``[sim]`` / ``[sim.camera]`` values always win over the preset.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from cell.config.schema import CellConfig
from estimator import CameraModel
from estimator.transforms import T_from_pose

Matrix4 = NDArray[np.float64]


@dataclass(frozen=True)
class RealisticOffsets:
    """How far the realistic world's truth sits from a cell's uncommissioned config."""

    mount_position_mm: tuple[float, float, float]
    mount_rotvec_rad: tuple[float, float, float]
    focal_scale: tuple[float, float]  # true fx/fy over configured fx/fy
    principal_offset_px: tuple[float, float]  # true cx/cy minus configured
    dist: tuple[float, float, float, float, float]  # true Brown-Conrady k1 k2 p1 p2 k3


# A hand-measured bracket (calipers, a square): 1-3 mm and a few tenths of a degree off;
# nominal intrinsics from a datasheet field of view: ~0.5-1 % in focal length, a few px in the
# principal point; a small-format M12 lens of the OAK class: mild barrel distortion.
REALISTIC = RealisticOffsets(
    mount_position_mm=(1.2, -0.8, 1.5),
    mount_rotvec_rad=(0.004, -0.003, 0.006),
    focal_scale=(1.008, 1.007),
    principal_offset_px=(3.5, -2.5),
    dist=(-0.045, 0.012, 0.0004, -0.0003, 0.0),
)


@dataclass(frozen=True)
class SimTruthValues:
    """What the simulated camera really is: its lens and where it sits on the flange."""

    world: str
    camera: CameraModel
    T_flange_camera: Matrix4


def resolve(config: CellConfig) -> SimTruthValues:
    """The simulated camera's true intrinsics and mount for ``config``."""
    sim, believed = config.sim, config.camera.model()
    T_believed = config.hand_eye.T_flange_camera.T()
    if sim.world == "realistic":
        o = REALISTIC
        fx, fy = believed.fx * o.focal_scale[0], believed.fy * o.focal_scale[1]
        cx, cy = believed.cx + o.principal_offset_px[0], believed.cy + o.principal_offset_px[1]
        dist: tuple[float, ...] = o.dist
        T_mount = T_believed @ T_from_pose(np.array(o.mount_position_mm),
                                           np.array(o.mount_rotvec_rad))
    else:
        fx, fy, cx, cy = believed.fx, believed.fy, believed.cx, believed.cy
        dist = tuple(believed.dist)
        T_mount = T_believed
    sc = sim.camera
    camera = CameraModel(
        sc.fx if sc.fx is not None else fx, sc.fy if sc.fy is not None else fy,
        sc.cx if sc.cx is not None else cx, sc.cy if sc.cy is not None else cy,
        tuple(sc.dist) if sc.dist is not None else dist, believed.width, believed.height)
    if sim.T_flange_camera is not None:
        T_mount = sim.T_flange_camera.T()
    return SimTruthValues(sim.world, camera, np.asarray(T_mount, dtype=float))
