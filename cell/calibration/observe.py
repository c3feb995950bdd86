"""What a calibration view shows: the target's matched points and the pose they give alone.

Shared by the guided routine (live frames) and the offline solve of a saved dataset, so a
dataset the routine wrote is re-solved from exactly the observations the routine made.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from cell.error_codes import ErrorCode
from cell.errors import CellError
from estimator import CameraModel, EstimationError, Target
from estimator.calib.board import Board, board_pose, detect_board

Matrix4 = NDArray[np.float64]


@dataclass(frozen=True)
class Observation:
    """The target in one image: matched points and the pose they give on their own."""

    object_points_mm: NDArray[np.float64]  # (N, 3) in the target frame
    image_points_px: NDArray[np.float64]  # (N, 2)
    T_camera_board: Matrix4
    rms_px: float


Observer = Callable[[NDArray[np.uint8], CameraModel], Observation]


class ObservationError(CellError):
    """The target was not found in the image; the message says why."""

    def __init__(self, message: str) -> None:
        super().__init__(ErrorCode.target_not_visible, message)


def board_observer(board: Board) -> Observer:
    """Observe a chessboard or circle grid."""

    def observe(image: NDArray[np.uint8], camera: CameraModel) -> Observation:
        pts = detect_board(board, image)
        if pts is None:
            raise ObservationError(f"no complete {board.cols}x{board.rows} {board.kind} in view")
        pose = board_pose(board, pts, camera)
        return Observation(board.object_points_mm(), pts, pose.T_camera_board, pose.rms_px)

    return observe


def dot_target_observer(target: Target, min_dots: int | None = None) -> Observer:
    """Observe the cell's dot target with the estimator (blobs, matching, bias-corrected pose).

    All dots are required by default: a missing dot is usually a dot at the image border,
    where its centre is the least trustworthy.
    """
    from estimator.blobs import detect_blobs
    from estimator.correspondence import match_blobs

    needed = target.n_points if min_dots is None else min_dots

    def observe(image: NDArray[np.uint8], camera: CameraModel) -> Observation:
        blobs = detect_blobs(image, target.polarity)
        try:
            match = match_blobs([(b.u, b.v) for b in blobs], target, camera, max_missing=0
                                if needed >= target.n_points else target.n_points - needed)
        except EstimationError as err:
            raise ObservationError(err.message) from err
        pose = match.pose
        pts = pose.image_points_px
        if pts is None:
            raise ObservationError("the estimator returned no image points")
        ids = np.asarray(match.model_ids, dtype=int)
        return Observation(target.points_mm[ids], np.asarray(pts, dtype=float).reshape(-1, 2),
                           pose.T_camera_target, float(pose.rms_px))

    return observe
