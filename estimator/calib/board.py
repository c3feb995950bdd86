"""Calibration boards: their 3-D model and their detection in a grey image.

Hand-eye calibration compares board poses across views, so every view must label the corners
the same way. OpenCV's detectors may return a chessboard's corners in either of two 180-degree
orders; :func:`detect_board` puts them in one canonical order (the first inner square is the
dark one) whenever the board's colouring can tell the two orders apart.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import cv2
import numpy as np
from numpy.typing import NDArray

from estimator.camera import CameraModel

BoardKind = Literal["chessboard", "circles", "acircles"]


@dataclass(frozen=True)
class Board:
    """A planar calibration board in its own frame (mm, z = 0, +z into the board).

    ``cols`` x ``rows`` counts inner corners for a chessboard (OpenCV's pattern size) and
    circles for circle grids. ``pitch_mm`` is the square size, or the circle spacing along a row.
    """

    kind: BoardKind
    cols: int
    rows: int
    pitch_mm: float

    def __post_init__(self) -> None:
        if self.kind not in ("chessboard", "circles", "acircles"):
            raise ValueError(
                f"board kind must be chessboard, circles or acircles, not {self.kind!r}"
            )
        if self.cols < 2 or self.rows < 2:
            raise ValueError(
                f"a board needs at least 2 x 2 features, got {self.cols} x {self.rows}"
            )
        if not self.pitch_mm > 0:
            raise ValueError(f"pitch_mm must be positive, got {self.pitch_mm}")

    @property
    def pattern_size(self) -> tuple[int, int]:
        return (self.cols, self.rows)

    @property
    def n_points(self) -> int:
        return self.cols * self.rows

    def object_points_mm(self) -> NDArray[np.float64]:
        """(N, 3) feature positions in detection order: row by row, ``cols`` per row."""
        j, i = np.mgrid[0 : self.rows, 0 : self.cols]
        x = i.astype(float)
        if self.kind == "acircles":
            # OpenCV's asymmetric grid: every other row is shifted by half a period.
            x = 2.0 * i + (j % 2)
            return np.column_stack(
                (x.ravel() * self.pitch_mm / 2.0, j.ravel() * self.pitch_mm / 2.0,
                 np.zeros(x.size))
            )
        return np.column_stack(
            (x.ravel() * self.pitch_mm, j.ravel() * self.pitch_mm, np.zeros(x.size))
        )


def chessboard(cols: int, rows: int, square_mm: float) -> Board:
    return Board("chessboard", cols, rows, square_mm)


def detect_board(board: Board, image: NDArray[np.uint8]) -> NDArray[np.float64] | None:
    """Sub-pixel feature positions (N, 2) in the order of :meth:`Board.object_points_mm`.

    Returns None when the whole board is not found (a partial board is useless for these
    solvers, which need every feature matched).
    """
    if image.ndim != 2:
        image = np.asarray(cv2.cvtColor(image, cv2.COLOR_BGR2GRAY), dtype=np.uint8)
    if board.kind == "chessboard":
        return _detect_chessboard(board, image)
    flags = cv2.CALIB_CB_SYMMETRIC_GRID if board.kind == "circles" else cv2.CALIB_CB_ASYMMETRIC_GRID
    found, centres = cv2.findCirclesGrid(image, board.pattern_size, flags=flags)
    if not found or centres is None:
        return None
    return np.asarray(centres, dtype=float).reshape(-1, 2)


def _detect_chessboard(board: Board, image: NDArray[np.uint8]) -> NDArray[np.float64] | None:
    flags = cv2.CALIB_CB_ADAPTIVE_THRESH | cv2.CALIB_CB_NORMALIZE_IMAGE
    found, corners = cv2.findChessboardCorners(image, board.pattern_size, flags=flags)
    if not found or corners is None:
        # The sector-based detector copes with blur and uneven light where the classic fails.
        found, corners = cv2.findChessboardCornersSB(image, board.pattern_size)
        if not found or corners is None:
            return None
    else:
        criteria = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_MAX_ITER, 50, 1e-3)
        corners = cv2.cornerSubPix(image, corners, (5, 5), (-1, -1), criteria)
    pts = np.asarray(corners, dtype=float).reshape(-1, 2)
    return _canonical_order(board, image, pts)


def _canonical_order(
    board: Board, image: NDArray[np.uint8], pts: NDArray[np.float64]
) -> NDArray[np.float64]:
    """Reverse the corner order when the first inner square is the light one.

    Reversing is the 180-degree relabelling; it is only decisive when the two inner squares
    compared (first and last) have different colours, i.e. when cols + rows is odd.
    """
    if (board.cols + board.rows) % 2 == 0:
        return pts
    grid = np.mgrid[0 : board.rows, 0 : board.cols][::-1].reshape(2, -1).T.astype(np.float32)
    found, _ = cv2.findHomography(grid, pts.astype(np.float32))
    if found is None:
        return pts
    H = np.asarray(found, dtype=float)
    first = _mean_grey(image, H, 0.5, 0.5)
    last = _mean_grey(image, H, board.cols - 1.5, board.rows - 1.5)
    return pts if first <= last else pts[::-1].copy()


def _mean_grey(image: NDArray[np.uint8], H: NDArray[np.float64], gx: float, gy: float) -> float:
    """Mean grey level over the middle of the square centred at grid position (gx, gy)."""
    offs = np.linspace(-0.25, 0.25, 5)
    sx, sy = np.meshgrid(gx + offs, gy + offs)
    src = np.column_stack((sx.ravel(), sy.ravel())).reshape(-1, 1, 2)
    uv = cv2.perspectiveTransform(src, H).reshape(-1, 2)
    h, w = image.shape
    u = np.clip(np.rint(uv[:, 0]).astype(int), 0, w - 1)
    v = np.clip(np.rint(uv[:, 1]).astype(int), 0, h - 1)
    return float(image[v, u].mean())


@dataclass(frozen=True)
class BoardPose:
    """The board seen from the camera in one image, with how well the pose explains the image."""

    T_camera_board: NDArray[np.float64]  # 4x4, mm
    rms_px: float
    residuals_px: NDArray[np.float64]  # per-feature reprojection error (N,)


def board_pose(
    board: Board, image_points_px: NDArray[np.float64], camera: CameraModel
) -> BoardPose:
    """Maximum-likelihood board pose: IPPE (exact for planes) seeds Levenberg-Marquardt."""
    obj = board.object_points_mm()
    img = np.asarray(image_points_px, dtype=float).reshape(-1, 2)
    if len(img) != len(obj):
        raise ValueError(f"expected {len(obj)} board features, got {len(img)}")
    K, dist = camera.K, camera.dist_coeffs
    ok, rvec, tvec = cv2.solvePnP(obj, img, K, dist, flags=cv2.SOLVEPNP_IPPE)
    if not ok:
        raise ValueError("solvePnP found no board pose")
    rvec, tvec = cv2.solvePnPRefineLM(obj, img, K, dist, rvec, tvec)
    proj, _ = cv2.projectPoints(obj, rvec, tvec, K, dist)
    res = np.linalg.norm(proj.reshape(-1, 2) - img, axis=1)
    T = np.eye(4)
    T[:3, :3] = cv2.Rodrigues(rvec)[0]
    T[:3, 3] = np.asarray(tvec, dtype=float).ravel()
    return BoardPose(T, float(np.sqrt(np.mean(res**2))), res)
