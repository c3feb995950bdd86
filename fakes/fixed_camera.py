"""A simulated fixed camera (eye-to-hand): it stands in the cell and watches the arm work.

The same sensor as :class:`fakes.sim_camera.SimCamera` (clock, faults, exposure, noise), but its
pose is ``T_base_camera`` whatever the arm does; the arm's flange pose at mid-exposure still
matters for two things a fixed camera sees and an eye-in-hand one does not:

- the tool body: a cylinder of ``tool_radius_mm`` from ``WRIST_MM`` behind the flange to the
  TCP, drawn over the scene, so an arm that moves between the camera and the target hides dots
  (the cell has to cope with that occlusion as on a real cell);
- a calibration plate clamped to the tool (``T_flange_board``, the dot layout of the world's
  first part, the cell's target): while it is mounted the camera sees that plate, carried by
  the arm, and the parts are off the table (one plate of the layout in view, as the calibration
  procedure asks).
"""

from __future__ import annotations

import cv2
import numpy as np
from numpy.typing import NDArray

from estimator import CameraModel, Target
from estimator.transforms import invert_T
from fakes.parts import SimParts
from fakes.sim_camera import PoseSource, SimCamera, _Exposure

Matrix4 = NDArray[np.float64]

WRIST_MM = 120.0  # how far the occluding body reaches behind the flange (the UR's wrist 3)
TOOL_LEVEL = 70.0  # grey level of the tool body: dark anodised metal
_RING_POINTS = 24


class FixedSimCamera(SimCamera):
    """Renders the parts (or the tool's plate) from a fixed ``T_base_camera``; the tool
    hides what is behind it."""

    def __init__(
        self, camera: CameraModel, parts: SimParts, T_base_camera: Matrix4,
        flange_source: PoseSource, T_flange_tcp: Matrix4, *,
        tool_radius_mm: float = 30.0, T_flange_board: Matrix4 | None = None,
        reported_camera: CameraModel | None = None, **options: float | int | None,
    ) -> None:
        super().__init__(camera, parts, np.asarray(T_base_camera, dtype=float),
                         flange_source, reported_camera=reported_camera,
                         **options)  # type: ignore[arg-type]
        self.board: Target = parts.first_layout()
        self.T_base_camera = np.array(T_base_camera, dtype=float)
        self.T_flange_tcp = np.array(T_flange_tcp, dtype=float)
        self.tool_radius_mm = float(tool_radius_mm)
        self._T_flange_board = None if T_flange_board is None else np.array(T_flange_board,
                                                                             dtype=float)
        self._tooled: tuple[int, bool, NDArray[np.uint8]] | None = None

    def set_tool_board(self, T_flange_board: Matrix4 | None) -> None:
        """Clamp the calibration plate to the tool at ``T_flange_board`` (None: take it off)."""
        T = None if T_flange_board is None else np.array(T_flange_board, dtype=float)
        if T is not None and (T.shape != (4, 4) or not np.all(np.isfinite(T))):
            raise ValueError("T_flange_board must be a finite 4x4 transform")
        with self._cond:
            self._T_flange_board = T

    def _mount_locked(self) -> Matrix4:
        return self.T_base_camera

    def _set_mount_locked(self, T_mount: Matrix4) -> None:
        self.T_base_camera = self.T_flange_camera = T_mount

    @property
    def T_flange_board(self) -> Matrix4 | None:
        with self._cond:
            return None if self._T_flange_board is None else self._T_flange_board.copy()

    def _view(self, T_base_flange: Matrix4, t_s: float
              ) -> tuple[Matrix4, list[tuple[Target, Matrix4]]]:
        if self._T_flange_board is not None:
            return self.T_base_camera, [(self.board, T_base_flange @ self._T_flange_board)]
        return self.T_base_camera, self.parts.scene_at(t_s, T_base_flange)

    def _render(self, exp: _Exposure) -> NDArray[np.uint8]:
        with self._cond:
            board = self._T_flange_board is not None
        cached = self._tooled
        if cached is not None and cached[:2] == (exp.sequence, board):
            return cached[2]
        image = super()._render(exp)
        # The plate on the tool faces the camera and covers the tool's end; a covered lens
        # shows nothing.
        if not (exp.blocked or board or exp.T_base_flange is None or exp.T_base_camera is None
                or self.tool_radius_mm <= 0):
            outline = self.tool_outline_px(exp.T_base_flange, exp.T_base_camera, exp.lens)
            if outline is not None:
                image = draw_tool(image, outline)
        # the frame with the tool, so that asking again for it (live view and loop alike)
        # neither copies 12 MP nor draws again
        self._tooled = (exp.sequence, board, image)
        return image

    def tool_outline_px(self, T_base_flange: Matrix4, T_base_camera: Matrix4, lens: CameraModel
                        ) -> NDArray[np.float64] | None:
        """The tool body's image through ``lens`` from ``T_base_camera`` (convex hull of its
        end rings), None when not in front."""
        T_f = np.asarray(T_base_flange, dtype=float)
        axis = T_f[:3, :3]
        ang = np.linspace(0.0, 2.0 * np.pi, _RING_POINTS, endpoint=False)
        ring = np.column_stack((np.cos(ang), np.sin(ang), np.zeros_like(ang))) \
            * self.tool_radius_mm
        ends = [np.array([0.0, 0.0, -WRIST_MM]), self.T_flange_tcp[:3, 3]]
        pts_flange = np.vstack([ring + e for e in ends])
        pts_base = pts_flange @ axis.T + T_f[:3, 3]
        T_cb = invert_T(T_base_camera)
        cam = pts_base @ T_cb[:3, :3].T + T_cb[:3, 3]
        if np.any(cam[:, 2] <= 1.0):
            return None
        px = lens.project(cam)
        hull = cv2.convexHull(px.astype(np.float32))
        return np.asarray(hull, dtype=np.float64).reshape(-1, 2)



def draw_tool(image: NDArray[np.uint8], outline_px: NDArray[np.float64]) -> NDArray[np.uint8]:
    """A copy of ``image`` with the tool body (its convex outline, pixels) filled anti-aliased
    over it: the rendered frame stays as it was for whoever holds it."""
    out = image.copy()
    cv2.fillConvexPoly(out, np.round(outline_px * 16).astype(np.int32), int(TOOL_LEVEL),
                       cv2.LINE_AA, 4)
    return out
