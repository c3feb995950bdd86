"""Frames showing several dot plates at once, with each plate's true pose.

Each plate is rendered alone on a flat background without noise or lighting gradient
(:func:`fakes.render.render_target`); the frame is the background plus every plate's
difference from it, then the sensor noise. Plates that do not overlap in the image come out
exactly as a single render draws them.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray
from scipy.spatial.transform import Rotation

from estimator import CameraModel, Target
from estimator.transforms import make_T
from fakes.render import render_target

BACKGROUND = 110.0


@dataclass(frozen=True)
class Plate:
    layout: str
    target: Target
    T_camera_target: NDArray[np.float64]


def render_plates(camera: CameraModel, plates: list[Plate], rng: np.random.Generator,
                  noise_std: float = 1.5) -> NDArray[np.uint8]:
    """One grey frame showing every plate."""
    acc = np.full((camera.height, camera.width), BACKGROUND, np.float64)
    for p in plates:
        img = render_target(camera, p.target, p.T_camera_target, noise_std=0.0,
                            lighting_gradient=0.0, background=BACKGROUND, rng=rng)
        acc += img.astype(np.float64) - BACKGROUND
    acc += rng.normal(0.0, noise_std, acc.shape)
    return np.asarray(np.clip(acc + 0.5, 0, 255), dtype=np.uint8)


def plate_at(camera: CameraModel, target: Target, centre_px: tuple[float, float],
             distance_mm: float, spin_deg: float, tilt_deg: float = 0.0,
             tilt_axis_deg: float = 0.0) -> NDArray[np.float64]:
    """The pose putting the layout's dot centroid on ``centre_px`` at ``distance_mm``,
    spun about its normal and tilted about an in-plane axis."""
    a = np.radians(tilt_axis_deg)
    tilt = Rotation.from_rotvec(np.radians(tilt_deg) * np.array([np.cos(a), np.sin(a), 0.0]))
    R = (tilt * Rotation.from_euler("z", spin_deg, degrees=True)).as_matrix()
    ray = np.array([(centre_px[0] - camera.cx) / camera.fx,
                    (centre_px[1] - camera.cy) / camera.fy, 1.0])
    centre = target.points_mm.mean(axis=0)
    return make_T(R, ray * distance_mm - R @ centre)
