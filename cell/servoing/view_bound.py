"""How far the TCP may truly be from where a view was taught, when the view says it is there.

The view's error ``e = s - s*`` maps to the TCP's remaining motion through the pseudo-inverse
of the interaction matrix and the lever to the TCP (:func:`cell.servoing.ibvs.
remaining_motion`). Its uncertainty maps the same way: each image coordinate's error, of the
taught view and of the view now, moves the TCP by that coordinate's column of the map. Two
kinds of error are in every dot's centre, both in pixels per image coordinate:

- noise, different in every frame: its share falls with the frames each view averages (the
  taught view's samples, the loop's window);
- bias, the same in every frame of one pose (a dot's centre is pulled towards the pixel grid
  by an amount that depends on where in the pixel it lies): averaging does not remove it, and
  the taught view and the view now each carry their own.

A planar target seen from afar has one weak direction, a turn about a point near the target,
that moves the dots by a hundredth of a pixel per tenth of a millimetre at the TCP (measured
at 456 mm in the simulated cell: 0.40 mm / 0.068 deg moved the dots 0.003-0.017 px). There the
bias alone makes the view's claim tenths of a millimetre wide, however still the arm and
however many frames the loop averages; the bound says so instead of claiming the tolerance.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from cell.servoing.ibvs import (
    MIN_FEATURES,
    Features,
    InteractionFrom,
    features_from_view,
    interaction_of,
)
from estimator import CameraModel, PoseResult

Matrix = NDArray[np.float64]
COVERAGE_SIGMAS = 2.0  # the bound is this many standard deviations of the TCP's error


@dataclass(frozen=True)
class Resolution:
    """The TCP's error a view's uncertainty allows (``COVERAGE_SIGMAS`` of it): mm and deg."""

    mm: float
    deg: float


def tcp_map(current: Features, desired: Features, which: InteractionFrom,
            T_camera_tcp: Matrix) -> tuple[Matrix, Matrix]:
    """``(A_mm (3, 2N), A_rad (3, 2N))``: the TCP point's displacement and the rotation the
    remaining motion takes per unit of each normalised feature coordinate's error."""
    step = np.linalg.pinv(interaction_of(current, desired, which))  # (6, 2N)
    r = np.asarray(T_camera_tcp[:3, 3], dtype=float)
    lever = np.array([[0.0, -r[2], r[1]], [r[2], 0.0, -r[0]], [-r[1], r[0], 0.0]])
    # dp + dtheta x r = dp - r x dtheta
    return np.asarray(step[:3] - lever @ step[3:], dtype=float), np.asarray(step[3:])


def resolution(current: Features, desired: Features, which: InteractionFrom,
               T_camera_tcp: Matrix, focal_px: float, noise_px: float, bias_px: float,
               current_frames: int) -> Resolution:
    """What the view resolves at the TCP: ``noise_px`` (one frame's, per image coordinate)
    over ``current_frames`` and the taught view's ``desired.frames``, and ``bias_px`` in
    each of the two views."""
    a_mm, a_rad = tcp_map(current, desired, which, T_camera_tcp)
    var = (noise_px ** 2 * (1.0 / max(current_frames, 1) + 1.0 / max(desired.frames, 1))
           + 2.0 * bias_px ** 2) / focal_px ** 2
    sigma = COVERAGE_SIGMAS * float(np.sqrt(var))
    return Resolution(sigma * float(np.linalg.norm(a_mm)),
                      float(np.degrees(sigma * np.linalg.norm(a_rad))))


def frame_noise_px(errors: list[Matrix], focal_px: float) -> float:
    """One frame's noise per image coordinate (px), from a window of consecutive errors
    ``s - s*`` (normalised, (N, 2) each): their scatter about a straight line through the
    window (the arm's steady creep is not noise; any other motion counts, which only widens
    the bound)."""
    n = len(errors)
    if n < 3:
        return 0.0
    stack = np.stack(errors).reshape(n, -1)
    t = np.column_stack([np.ones(n), np.arange(n, dtype=float)])
    fit, *_ = np.linalg.lstsq(t, stack, rcond=None)
    residual = stack - t @ fit
    return float(np.sqrt(np.sum(residual ** 2) / ((n - 2) * stack.shape[1]))) * focal_px


def pose_resolution(camera: CameraModel, result: PoseResult, target_points_mm: Matrix,
                    T_camera_tcp: Matrix, bias_px: float, frames: int) -> Resolution | None:
    """What a pose estimate from ``frames`` averaged frames of one viewpoint resolves at the
    TCP, against a goal taught the same way from one frame (the estimate moves with the dots'
    centres as the view's remaining motion does, to first order). None: no image points."""
    if result.image_points_px is None or not result.matched_ids:
        return None
    view = features_from_view(camera, result.matched_ids, result.image_points_px,
                              result.T_camera_target, target_points_mm)
    if len(view.ids) < MIN_FEATURES:
        return None
    return resolution(view, view, "current", T_camera_tcp, camera.fx, bias_px, bias_px, frames)
