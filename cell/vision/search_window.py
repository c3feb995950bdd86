"""Where to search the next frame: a window around the dots last seen, as wide as they can
have moved since.

The estimator's full search labels the whole frame; on the fixed camera's 12 MP sensor that
costs hundreds of milliseconds once the tool hides a dot (the fast coarse pass then cannot
account for every dot and the whole frame is labelled at full resolution), and a closed loop
whose frames each take that long stalls. After a frame that showed the dots, the next one
needs only a window around them (the estimator searches it first and falls back to the whole
frame when the window does not account for every dot, :mod:`estimator.window`).

How wide: the dots' own size, plus what they can have moved in the image between the two
exposures. The arm's motion between them is known exactly (its pose history at both
exposure times); the target's own motion is not, so ``target_speed_mm_s`` bounds it:

- fixed camera: a dot moves with the arm only if the arm carries it (the plate on the tool);
  the bound takes the arm's motion at the dots anyway: the TCP's shift plus its turn times the
  lever from the TCP to the farthest dot;
- camera on the flange: the camera's own shift, plus its turn, which sweeps the whole image
  (the turn times the depth, in millimetres at the target).

Millimetres at the target become pixels at the nearest dot's depth (the largest scale).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from estimator import CameraModel, PoseResult
from estimator.blobs import Window
from estimator.window import search_window

Matrix4 = NDArray[np.float64]

TARGET_SPEED_MM_S = 100.0  # the target's own motion the window allows for (a conveyor)
DOT_MARGIN = 1.5  # dot diameters around the dots' centres, whatever the motion
MAX_AGE_S = 2.0  # an older sighting does not bound where the dots are now


@dataclass(frozen=True)
class _Seen:
    points_px: NDArray[np.float64]
    dot_px: float  # the largest dot's major axis
    exposure_s: float
    T_base_tcp: Matrix4
    px_per_mm: float  # at the nearest dot
    reach_mm: float  # fixed: TCP to the farthest dot; hand: camera to the farthest dot
    camera_lever_mm: float  # hand: TCP to the camera (0 for a fixed camera)


class SearchWindows:
    """The window policy of one estimator: remembers the last sighting. Not thread-safe (the
    locator calls it under its estimator lock)."""

    def __init__(self, fixed_camera: bool, *, target_speed_mm_s: float = TARGET_SPEED_MM_S,
                 max_age_s: float = MAX_AGE_S) -> None:
        self.fixed_camera = fixed_camera
        self.target_speed_mm_s = float(target_speed_mm_s)
        self.max_age_s = float(max_age_s)
        self._seen: _Seen | None = None

    def forget(self) -> None:
        self._seen = None

    def seen(self, result: PoseResult, model_points_mm: NDArray[np.float64],
             camera: CameraModel, exposure_s: float, T_base_tcp: Matrix4,
             T_base_camera: Matrix4) -> None:
        """A frame showed the dots (``model_points_mm``: the whole target's, target frame):
        remember where (the matched dots and where the pose puts all of them, hidden ones
        included), how large, and where the arm was."""
        self._seen = None
        pts = result.image_points_px
        if pts is None or not result.matched_blobs:
            return
        T = result.T_camera_target
        P = np.asarray(model_points_mm, dtype=float).reshape(-1, 3)
        Pc = P @ T[:3, :3].T + T[:3, 3]
        if Pc[:, 2].min() <= 0:
            return
        if self.fixed_camera:
            dots_base = Pc @ T_base_camera[:3, :3].T + T_base_camera[:3, 3]
            reach = float(np.linalg.norm(dots_base - T_base_tcp[:3, 3], axis=1).max())
            lever = 0.0
        else:
            reach = float(Pc[:, 2].max())
            lever = float(np.linalg.norm(T_base_camera[:3, 3] - T_base_tcp[:3, 3]))
        where = np.vstack((np.asarray(pts, dtype=float).reshape(-1, 2), camera.project(Pc)))
        self._seen = _Seen(where,
                           max(b.major_axis_px for b in result.matched_blobs),
                           float(exposure_s), np.array(T_base_tcp, dtype=float),
                           float(max(camera.fx, camera.fy) / Pc[:, 2].min()), reach, lever)

    def window(self, exposure_s: float, T_base_tcp: Matrix4, width: int, height: int
               ) -> Window | None:
        """Where the dots can be in a frame exposed at ``exposure_s`` with the arm at
        ``T_base_tcp``; None: search the whole frame."""
        s = self._seen
        if s is None:
            return None
        dt = float(exposure_s) - s.exposure_s
        if not 0.0 <= dt <= self.max_age_s:
            return None
        shift_mm = float(np.linalg.norm(T_base_tcp[:3, 3] - s.T_base_tcp[:3, 3]))
        turn_rad = _angle(s.T_base_tcp[:3, :3].T @ T_base_tcp[:3, :3])
        if self.fixed_camera:
            motion_mm = shift_mm + turn_rad * s.reach_mm
        else:
            motion_mm = shift_mm + turn_rad * (s.camera_lever_mm + s.reach_mm)
        motion_mm += self.target_speed_mm_s * dt
        margin = DOT_MARGIN * s.dot_px + s.px_per_mm * motion_mm
        return search_window(s.points_px, margin, width, height)


def _angle(R: NDArray[np.float64]) -> float:
    return float(np.arccos(np.clip((np.trace(R) - 1.0) / 2.0, -1.0, 1.0)))
