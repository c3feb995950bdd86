"""The image-based visual servo law (IBVS) with point features.

Pure maths, no arm and no camera, so it is unit-tested on its own. The features are the dots'
image points in normalised coordinates (pixels undistorted through the lens model), so the
law is independent of the focal length in the first order: the loop drives the image error
``e = s - s*`` to zero, and a view that matches the taught one puts the camera where it was
when taught, whatever the hand-eye transform or the intrinsics' small errors.

The law is the classic exponential decrease of the error, ``v_c = -lambda L^+ e``, with ``L``
the interaction matrix of points (two rows per point, depth ``Z`` in mm, so the camera twist
comes out in mm/s and rad/s). ``L`` is built from the current features and depths, from the
desired ones, or from their mean (``0.5 (L(s, Z) + L(s*, Z*))``, which behaves best for large
rotations: the camera path stays straighter than with the current one and the image path
straighter than with the desired one). The gain adapts to the error like ViSP's
``vpAdaptiveGain``: ``lambda(x) = (l0 - linf) exp(-slope0 x / (l0 - linf)) + linf`` with ``x``
the largest feature error, ``l0`` the gain at zero error, ``linf`` far away and ``slope0`` its
slope at zero.

With a fixed camera (eye-to-hand) the features are dots carried by the tool (a plate clamped to
it) and the camera stands still: the image moves with the camera's motion relative to the
plate, which is minus the plate's own twist, so ``s_dot = -L V`` and the plate's commanded
twist in the camera frame is ``V = +lambda L^+ e`` (:func:`carried_twist`): the law's twist with
the sign turned. Everything else is shared: the interaction matrix, the gain, the mapping to
the TCP (a rigid body's twist about the camera's origin, whoever carries what).

The camera twist (camera frame, about the camera's origin) becomes the base-frame twist of the
TCP (the velocity of the TCP point and the angular velocity, which is what the guarded arm
takes) through the adjoint of the camera's pose in the base frame and the lever from the
camera's origin to the TCP. A wrong hand-eye transform only bends the path, not the point the
image error vanishes at.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Literal

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.spatial.transform import Rotation

from estimator import CameraModel

Vec = NDArray[np.float64]
Matrix = NDArray[np.float64]
InteractionFrom = Literal["current", "desired", "mean"]
MIN_FEATURES = 4  # fewer matched dots than this and the law is not used (target_lost)


@dataclass(frozen=True)
class AdaptiveGain:
    """``lambda(x) = (l0 - linf) exp(-slope0 x / (l0 - linf)) + linf`` (1/s; x unitless)."""

    at_zero_per_s: float
    at_infinity_per_s: float
    slope_at_zero: float

    def __call__(self, error_inf_norm: float) -> float:
        span = self.at_zero_per_s - self.at_infinity_per_s
        if abs(span) < 1e-12 or self.slope_at_zero == 0.0:
            return self.at_zero_per_s
        return float(span * np.exp(-self.slope_at_zero * error_inf_norm / span)
                     + self.at_infinity_per_s)


@dataclass(frozen=True)
class LatencyCappedGain:
    """The adaptive gain, capped at ``product / latency_s``: a loop that acts on information
    ``latency_s`` old is an integrator behind a delay, which rings when ``lambda * delay``
    nears 1 (phase margin ``90 deg - lambda * delay rad``); at 0.4 the margin is 67 deg and the
    step response does not overshoot by more than a few per cent, whatever the host's load
    makes the delay."""

    gain: AdaptiveGain
    latency_s: float
    product: float

    @property
    def cap_per_s(self) -> float:
        return self.product / max(self.latency_s, 1e-3)

    def __call__(self, error_inf_norm: float) -> float:
        return min(self.gain(error_inf_norm), self.cap_per_s)


@dataclass(frozen=True)
class Features:
    """Point features of one view: normalised image points and depths, per dot id."""

    ids: tuple[int, ...]
    xy: Matrix  # (N, 2) normalised image coordinates
    depth_mm: Vec  # (N,) depth of each dot in the camera frame
    frames: int = 1  # averaged over this many frames: their random noise is that much smaller

    def subset(self, ids: tuple[int, ...]) -> Features:
        index = {d: k for k, d in enumerate(self.ids)}
        rows = [index[d] for d in ids]
        return Features(tuple(ids), self.xy[rows], self.depth_mm[rows], self.frames)


def normalised_points(camera: CameraModel, points_px: ArrayLike) -> Matrix:
    """Pixel coordinates (N, 2) to normalised coordinates (N, 2) through the lens model."""
    return camera.undistort_points(points_px)


def depths_mm(T_camera_target: Matrix, target_points_mm: ArrayLike) -> Vec:
    """The depth ``Z`` of each target point (N, 3, target frame) in the camera frame."""
    P = np.asarray(target_points_mm, dtype=float).reshape(-1, 3)
    return np.asarray(P @ T_camera_target[2, :3] + T_camera_target[2, 3], dtype=float)


def project_normalised(T_camera_target: Matrix, target_points_mm: ArrayLike) -> Matrix:
    """Normalised image points of target points seen from ``T_camera_target``."""
    P = np.asarray(target_points_mm, dtype=float).reshape(-1, 3)
    Pc = P @ T_camera_target[:3, :3].T + T_camera_target[:3, 3]
    return np.asarray(Pc[:, :2] / Pc[:, 2:3], dtype=float)


def features_from_view(camera: CameraModel, ids: ArrayLike, points_px: ArrayLike,
                       T_camera_target: Matrix, target_points_mm: ArrayLike) -> Features:
    """The features of one estimated view: the matched dots' measured image points
    (normalised) and their depths from the pose estimate."""
    id_list = tuple(int(i) for i in np.asarray(ids).reshape(-1))
    model = np.asarray(target_points_mm, dtype=float).reshape(-1, 3)[list(id_list)]
    return Features(id_list, normalised_points(camera, points_px),
                    depths_mm(T_camera_target, model))


def interaction_matrix(xy: ArrayLike, depth_mm: ArrayLike) -> Matrix:
    """The (2N, 6) interaction matrix of N image points: ``ds/dt = L v_c`` with the camera's
    twist ``v_c = [v mm/s, w rad/s]`` in the camera frame (the points fixed in the scene)."""
    p = np.asarray(xy, dtype=float).reshape(-1, 2)
    Z = np.asarray(depth_mm, dtype=float).reshape(-1)
    if np.any(Z <= 0) or not np.all(np.isfinite(Z)):
        raise ValueError("every feature needs a positive finite depth")
    x, y = p[:, 0], p[:, 1]
    L = np.zeros((2 * len(p), 6))
    L[0::2] = np.column_stack([-1 / Z, 0 * Z, x / Z, x * y, -(1 + x * x), y])
    L[1::2] = np.column_stack([0 * Z, -1 / Z, y / Z, 1 + y * y, -x * y, -x])
    return L


def feature_error(current: Features, desired: Features) -> Vec:
    """``s - s*`` stacked per point (x0, y0, x1, y1, ...), both for the same ids."""
    if current.ids != desired.ids:
        raise ValueError("current and desired features must be for the same dot ids")
    return np.asarray((current.xy - desired.xy).reshape(-1), dtype=float)


def camera_twist(current: Features, desired: Features, gain: Callable[[float], float],
                 interaction: InteractionFrom = "mean") -> Vec:
    """``v_c = -lambda(|e|_inf) L^+ e`` (camera frame, mm/s and rad/s)."""
    if len(current.ids) < MIN_FEATURES:
        raise ValueError(f"IBVS needs at least {MIN_FEATURES} points, got {len(current.ids)}")
    e = feature_error(current, desired)
    L = interaction_of(current, desired, interaction)
    lam = gain(float(np.max(np.abs(e))) if e.size else 0.0)
    return np.asarray(-lam * (np.linalg.pinv(L) @ e), dtype=float)


def carried_twist(current: Features, desired: Features, gain: Callable[[float], float],
                  interaction: InteractionFrom = "mean") -> Vec:
    """Eye-to-hand: the twist (camera frame, about its origin) to give the body that carries
    the dots, seen by a fixed camera: ``+lambda L^+ e``, the opposite of the camera twist
    :func:`camera_twist` asks for (the image sees only the relative motion)."""
    return -camera_twist(current, desired, gain, interaction)


def view_pose(features: Features, target_points_mm: ArrayLike) -> Matrix:
    """``T_camera_target`` of a recorded view: the rigid fit (SciPy's ``align_vectors``) of
    the target's dots to the view's 3-D points ``(x Z, y Z, Z)``."""
    model = np.asarray(target_points_mm, dtype=float).reshape(-1, 3)[list(features.ids)]
    seen = np.column_stack((features.xy * features.depth_mm[:, None], features.depth_mm))
    cm, cs = model.mean(axis=0), seen.mean(axis=0)
    rot, _ = Rotation.align_vectors(seen - cs, model - cm)
    T = np.eye(4)
    T[:3, :3] = rot.as_matrix()
    T[:3, 3] = cs - T[:3, :3] @ cm
    return T


def interaction_of(current: Features, desired: Features, which: InteractionFrom) -> Matrix:
    """The interaction matrix the law uses: of the current view, the desired one, or the mean."""
    if which == "current":
        return interaction_matrix(current.xy, current.depth_mm)
    if which == "desired":
        return interaction_matrix(desired.xy, desired.depth_mm)
    return 0.5 * (interaction_matrix(current.xy, current.depth_mm)
                  + interaction_matrix(desired.xy, desired.depth_mm))


def remaining_motion(current: Features, desired: Features, which: InteractionFrom,
                     T_camera_tcp: Matrix) -> tuple[float, float]:
    """How far the view says the TCP still is from where it was taught: the camera's
    Gauss-Newton step ``-L^+ e`` applied to the TCP point (mm) and its angle (deg).

    The image error alone hides the view's weakest direction (a turn about a point near the
    target moves the image by thousandths of a pixel per tenth of a millimetre); the pseudo-
    inverse weighs every direction by what it means in space, so this is the test that
    does not stop on a view that is right in pixels and wrong in millimetres."""
    step = -np.linalg.pinv(interaction_of(current, desired, which)) @ feature_error(current,
                                                                                 desired)
    dp = step[:3] + np.cross(step[3:], T_camera_tcp[:3, 3])
    return float(np.linalg.norm(dp)), float(np.degrees(np.linalg.norm(step[3:])))


def base_tcp_twist(v_camera: ArrayLike, T_base_camera: Matrix, T_base_tcp: Matrix) -> Vec:
    """The camera-frame twist as the base-frame twist of the TCP: ``w_b = R w_c`` and the TCP
    point's velocity ``R v_c + w_b x (p_tcp - p_camera)`` (rigid body, same angular rate)."""
    t = np.asarray(v_camera, dtype=float).reshape(6)
    R = T_base_camera[:3, :3]
    w = R @ t[3:]
    v = R @ t[:3] + np.cross(w, T_base_tcp[:3, 3] - T_base_camera[:3, 3])
    return np.concatenate([v, w])


def camera_twist_from_base(twist_base_tcp: ArrayLike, T_base_camera: Matrix,
                           T_base_tcp: Matrix) -> Vec:
    """The inverse of :func:`base_tcp_twist`."""
    t = np.asarray(twist_base_tcp, dtype=float).reshape(6)
    R = T_base_camera[:3, :3]
    w_b = t[3:]
    v_cam = t[:3] + np.cross(w_b, T_base_camera[:3, 3] - T_base_tcp[:3, 3])
    return np.concatenate([R.T @ v_cam, R.T @ w_b])


def limit_twist(twist: ArrayLike, previous: ArrayLike, dt_s: float, max_speed_mm_s: float,
                max_angular_speed_rad_s: float, accel_mm_s2: float, accel_rad_s2: float
                ) -> Vec:
    """Cap the base-frame twist's speeds, scaling translation and rotation together (the
    direction of the law's step is kept: scaling one part alone would turn the image path),
    then limit its change from the previous tick by the accelerations, each part apart."""
    t = np.asarray(twist, dtype=float).reshape(6)
    prev = np.asarray(previous, dtype=float).reshape(6)
    lin, ang = float(np.linalg.norm(t[:3])), float(np.linalg.norm(t[3:]))
    scale = min(1.0, max_speed_mm_s / lin if lin > 0 else 1.0,
                max_angular_speed_rad_s / ang if ang > 0 else 1.0)
    t = t * scale
    dt = max(float(dt_s), 0.0)
    out = np.empty(6)
    for sl, a in ((slice(0, 3), accel_mm_s2), (slice(3, 6), accel_rad_s2)):
        dv = t[sl] - prev[sl]
        n = float(np.linalg.norm(dv))
        step = a * dt
        out[sl] = t[sl] if n <= step else prev[sl] + dv * (step / n)
    return out


def predicted(features: Features, T_camera_now_camera_then: Matrix,
              target_points_camera_mm: ArrayLike) -> Features:
    """The features moved on by a small camera motion since they were measured: the measured
    points plus the change the motion makes to their projections (the motion from the arm's
    pose history; at rest it is the identity and the measured points are used as they are)."""
    P = np.asarray(target_points_camera_mm, dtype=float).reshape(-1, 3)
    Pn = P @ T_camera_now_camera_then[:3, :3].T + T_camera_now_camera_then[:3, 3]
    change = Pn[:, :2] / Pn[:, 2:3] - P[:, :2] / P[:, 2:3]
    return Features(features.ids, features.xy + change, Pn[:, 2].copy())


def image_error_px(current: Features, desired: Features, camera: CameraModel
                   ) -> tuple[float, float]:
    """RMS and max of the per-dot image distance in pixels (normalised error times the focal
    length: the error as the operator sees it in the image)."""
    d = (current.xy - desired.xy) * np.array([camera.fx, camera.fy])
    n = np.linalg.norm(d, axis=1)
    if not len(n):
        return float("nan"), float("nan")
    return float(np.sqrt(np.mean(n ** 2))), float(np.max(n))
