"""Rigid transforms as 4x4 homogeneous matrices in millimetres.

Naming convention used across the project: ``T_a_b`` maps points expressed in frame ``b`` into
frame ``a`` (so ``T_base_target = T_base_camera @ T_camera_target``). Rotation conversions are
delegated to SciPy; this module only fixes units and layouts so that no other module has to.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.spatial.transform import Rotation

Matrix4 = NDArray[np.float64]


def make_T(R: ArrayLike, t_mm: ArrayLike) -> Matrix4:
    """Build a 4x4 transform from a 3x3 rotation and a translation in mm."""
    T = np.eye(4)
    T[:3, :3] = np.asarray(R, dtype=float)
    T[:3, 3] = np.asarray(t_mm, dtype=float).reshape(3)
    return T


def invert_T(T: ArrayLike) -> Matrix4:
    """Inverse of a rigid transform, using R^T rather than a general matrix inverse."""
    T = np.asarray(T, dtype=float)
    R = T[:3, :3]
    out = np.eye(4)
    out[:3, :3] = R.T
    out[:3, 3] = -R.T @ T[:3, 3]
    return out


def T_from_pose(position_mm: ArrayLike, rotvec_rad: ArrayLike) -> Matrix4:
    """Transform from the project's JSON pose: position (mm) and rotation vector (rad)."""
    R = Rotation.from_rotvec(np.asarray(rotvec_rad, dtype=float).reshape(3)).as_matrix()
    return make_T(R, position_mm)


# Within this of pi a rotation's two rotation vectors (theta about u, 2 pi - theta about -u)
# read alike at the page's 0.1 deg (both "180.0"), so they are reported as one (canonical_rotvec).
PI_BAND_RAD = 1e-3
# An axis component smaller than this counts as zero when picking the sign at pi.
AXIS_ZERO = 1e-6


def canonical_rotvec(R: ArrayLike) -> NDArray[np.float64]:
    """The one rotation vector every report gives for the 3x3 rotation ``R``: angle in
    [0, pi] (SciPy's), except within ``PI_BAND_RAD`` of pi, where a rotation has two readings
    (theta about u, 2 pi - theta about -u; at exactly pi, pi about either): there the one
    whose axis has its first component above ``AXIS_ZERO`` in magnitude positive. Always the
    same rotation, never rounded to another one, so that angle may exceed pi by at most
    ``PI_BAND_RAD``. Only for reports: the UR wire pose (:func:`ur_pose_from_T`) keeps
    SciPy's reading, which a controller takes as well."""
    rotvec = Rotation.from_matrix(np.asarray(R, dtype=float).reshape(3, 3)).as_rotvec()
    angle = float(np.linalg.norm(rotvec))
    if np.pi - angle <= PI_BAND_RAD:
        axis = rotvec / angle
        if next((float(v) for v in axis if abs(v) > AXIS_ZERO), 1.0) < 0:
            rotvec = -axis * (2.0 * np.pi - angle)
    return rotvec + 0.0  # no -0.0 in a report


def pose_from_T(T: ArrayLike) -> tuple[list[float], list[float]]:
    """(position_mm, rotvec_rad) of a transform, as plain lists for JSON; the rotation vector
    is the canonical one (:func:`canonical_rotvec`), so one pose always reads the same."""
    T = np.asarray(T, dtype=float)
    return [float(v) for v in T[:3, 3]], [float(v) for v in canonical_rotvec(T[:3, :3])]


def pose_dict(T: ArrayLike) -> dict[str, list[float]]:
    """The pose object used in every JSON output: ``{"position_mm", "rotvec_rad"}``."""
    position_mm, rotvec_rad = pose_from_T(T)
    return {"position_mm": position_mm, "rotvec_rad": rotvec_rad}


def T_from_pose_dict(pose: dict[str, Sequence[float]]) -> Matrix4:
    """Inverse of :func:`pose_dict`."""
    return T_from_pose(pose["position_mm"], pose["rotvec_rad"])


def T_from_ur_pose(pose: Sequence[float]) -> Matrix4:
    """UR wire pose ``[x, y, z (m), rx, ry, rz (rad, rotation vector)]`` -> 4x4 in mm."""
    p = np.asarray(pose, dtype=float).reshape(6)
    return T_from_pose(p[:3] * 1000.0, p[3:])


def ur_pose_from_T(T: ArrayLike) -> list[float]:
    """4x4 in mm -> UR wire pose ``[x, y, z (m), rx, ry, rz (rad)]``: SciPy's rotation vector
    as it comes (angle in [0, pi]), not the reports' canonical one; a UR takes either."""
    T = np.asarray(T, dtype=float)
    rotvec = Rotation.from_matrix(T[:3, :3]).as_rotvec()
    return [float(v) / 1000.0 for v in T[:3, 3]] + [float(v) for v in rotvec]


def translation_T(x_mm: float = 0.0, y_mm: float = 0.0, z_mm: float = 0.0) -> Matrix4:
    """Pure translation."""
    return make_T(np.eye(3), [x_mm, y_mm, z_mm])


def pose_distance(T_a: ArrayLike, T_b: ArrayLike) -> tuple[float, float]:
    """(translation distance in mm, rotation angle in deg) between two transforms."""
    A = np.asarray(T_a, dtype=float)
    B = np.asarray(T_b, dtype=float)
    dt_mm = float(np.linalg.norm(A[:3, 3] - B[:3, 3]))
    dR = A[:3, :3].T @ B[:3, :3]
    angle_deg = float(np.degrees(np.linalg.norm(Rotation.from_matrix(dR).as_rotvec())))
    return dt_mm, angle_deg
