"""Rendered board images with known geometry, to check the calibration code end to end.

A flat texture of the board (mm-scaled) is warped into the image by the plane's homography
``K [r1 r2 t]``: exact perspective for an undistorted pinhole camera. Used by the tests and by
the simulated cell, whose camera model has no distortion.
"""

from __future__ import annotations

import cv2
import numpy as np
from numpy.typing import NDArray

from estimator.calib.board import Board
from estimator.camera import CameraModel

TEXTURE_PX_PER_MM = 6.0


def board_texture(board: Board, px_per_mm: float = TEXTURE_PX_PER_MM) -> tuple[
    NDArray[np.uint8], NDArray[np.float64]
]:
    """(texture image, 3x3 map from texture pixels to board-plane mm) with a white margin."""
    pitch = board.pitch_mm
    if board.kind == "chessboard":
        lo = np.array([-2.0 * pitch, -2.0 * pitch])
        hi = np.array([(board.cols + 1) * pitch, (board.rows + 1) * pitch])
    else:
        extent = board.object_points_mm()[:, :2]
        lo, hi = extent.min(axis=0) - pitch, extent.max(axis=0) + pitch
    size = np.ceil((hi - lo) * px_per_mm).astype(int)
    tex = np.full((size[1], size[0]), 255, np.uint8)
    # texture pixel centre (u, v) <-> board point lo + (u + 0.5, v + 0.5) / px_per_mm
    S = np.array([[1 / px_per_mm, 0, lo[0] + 0.5 / px_per_mm],
                  [0, 1 / px_per_mm, lo[1] + 0.5 / px_per_mm], [0, 0, 1]])
    to_px = np.linalg.inv(S)

    def px(x_mm: float, y_mm: float) -> tuple[int, int]:
        u, v, _ = to_px @ np.array([x_mm, y_mm, 1.0])
        return round(float(u)), round(float(v))

    if board.kind == "chessboard":
        for j in range(-1, board.rows):
            for i in range(-1, board.cols):
                if (i + j) % 2 == 0:  # the square right-below the first corner is dark
                    cv2.rectangle(tex, px(i * pitch, j * pitch),
                                  px((i + 1) * pitch, (j + 1) * pitch), 0, thickness=-1)
    else:
        shift = 4  # sub-pixel circle centres
        radius = round(0.25 * pitch * px_per_mm * (1 << shift))
        for x, y, _ in board.object_points_mm():
            u, v, _ = to_px @ np.array([x, y, 1.0])
            centre = (round(float(u) * (1 << shift)), round(float(v) * (1 << shift)))
            cv2.circle(tex, centre, radius, 0, -1, cv2.LINE_AA, shift)
    return tex, S


def render_board(
    board: Board,
    camera: CameraModel,
    T_camera_board: NDArray[np.float64],
    background: int = 90,
    noise_sigma: float = 0.0,
    seed: int = 0,
) -> NDArray[np.uint8]:
    """Grey image of the board seen from ``T_camera_board`` (distortion is not modelled)."""
    tex, S = board_texture(board)
    T = np.asarray(T_camera_board, dtype=float)
    H = camera.K @ np.column_stack((T[:3, 0], T[:3, 1], T[:3, 3])) @ S
    # Blurring the texture to the size of one image pixel avoids aliasing in the warp.
    h_tex, w_tex = tex.shape
    corners = np.array([[[0, 0]], [[w_tex, 0]], [[w_tex, h_tex]], [[0, h_tex]]], np.float64)
    imaged = cv2.perspectiveTransform(corners, H).reshape(-1, 2)
    scale = float(np.sqrt(cv2.contourArea(imaged.astype(np.float32)) / (w_tex * h_tex)))
    if scale < 1.0:
        tex = np.asarray(cv2.GaussianBlur(tex, (0, 0), 0.5 / scale), dtype=np.uint8)
    size = (camera.width, camera.height)
    img = cv2.warpPerspective(tex, H, size, flags=cv2.INTER_LINEAR,
                              borderMode=cv2.BORDER_CONSTANT, borderValue=background)
    mask = cv2.warpPerspective(np.full(tex.shape, 255, np.uint8), H, size, flags=cv2.INTER_LINEAR)
    out = np.where(mask > 0, img, background).astype(float)
    if noise_sigma > 0:
        out += np.random.default_rng(seed).normal(0.0, noise_sigma, out.shape)
    return np.clip(np.rint(out), 0, 255).astype(np.uint8)
