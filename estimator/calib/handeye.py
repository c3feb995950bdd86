"""Eye-in-hand calibration: solve ``A X = X B`` for ``X = T_flange_camera``, then refine.

For views i and j of a fixed board, ``T_base_board = T_base_flange_i X T_camera_board_i`` holds for
both, so the flange motion ``A = inv(T_base_flange_j) T_base_flange_i`` and the camera motion
``B = T_camera_board_j inv(T_camera_board_i)`` satisfy ``A X = X B``. Every pair of views gives
one such equation; the closed-form solvers (Tsai-Lenz, Park-Martin, Horaud-Dornaika) differ in how
they fit the rotation, and share the linear least-squares fit of the translation.

The closed forms minimise algebraic errors on motions; :func:`refine_joint` then minimises what
is actually measured - the pixel positions of every board corner in every view - over
``T_flange_camera`` and the fixed ``T_base_board`` (12 parameters).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass
from itertools import combinations

import numpy as np
from numpy.typing import NDArray
from scipy.optimize import least_squares
from scipy.spatial.transform import Rotation

from estimator.camera import CameraModel
from estimator.transforms import invert_T, make_T

Matrix4 = NDArray[np.float64]
Solver = Callable[[Sequence[Matrix4], Sequence[Matrix4]], Matrix4]

# Pairs whose rotation is smaller than this carry no usable axis; Tsai's paper drops them too.
MIN_PAIR_ROTATION_RAD = np.radians(0.5)


class HandEyeError(ValueError):
    """The views cannot determine the hand-eye transform; the message says what to change."""

    code = "hand_eye_degenerate"


def motion_pairs(
    T_base_flange: Sequence[Matrix4], T_camera_board: Sequence[Matrix4]
) -> list[tuple[Matrix4, Matrix4]]:
    """(A, B) for every pair of views with enough rotation between them."""
    if len(T_base_flange) != len(T_camera_board):
        raise HandEyeError(
            f"{len(T_base_flange)} robot poses but {len(T_camera_board)} board poses"
        )
    if len(T_base_flange) < 3:
        raise HandEyeError(f"need at least 3 views, got {len(T_base_flange)}")
    pairs = []
    for i, j in combinations(range(len(T_base_flange)), 2):
        A = invert_T(T_base_flange[j]) @ np.asarray(T_base_flange[i], dtype=float)
        B = np.asarray(T_camera_board[j], dtype=float) @ invert_T(T_camera_board[i])
        if _angle(A) >= MIN_PAIR_ROTATION_RAD:
            pairs.append((A, B))
    axes = np.array([Rotation.from_matrix(A[:3, :3]).as_rotvec() for A, _ in pairs])
    if len(pairs) < 2 or np.linalg.matrix_rank(axes, tol=1e-3 * max(np.abs(axes).max(), 1e-12)) < 2:
        raise HandEyeError(
            "the robot poses do not rotate about at least two different axes: "
            "add views tilted about another axis"
        )
    return pairs


def _angle(T: Matrix4) -> float:
    return float(np.linalg.norm(Rotation.from_matrix(T[:3, :3]).as_rotvec()))


def _skew(v: NDArray[np.float64]) -> NDArray[np.float64]:
    return np.array([[0.0, -v[2], v[1]], [v[2], 0.0, -v[0]], [-v[1], v[0], 0.0]])


def _translation(pairs: list[tuple[Matrix4, Matrix4]], R_X: NDArray[np.float64]) -> Matrix4:
    """Given R_X, ``(R_A - I) t_X = R_X t_B - t_A`` is linear in t_X: least squares over pairs."""
    M = np.vstack([A[:3, :3] - np.eye(3) for A, _ in pairs])
    rhs = np.concatenate([R_X @ B[:3, 3] - A[:3, 3] for A, B in pairs])
    t_X = np.linalg.lstsq(M, rhs, rcond=None)[0]
    return make_T(R_X, t_X)


def solve_tsai(T_base_flange: Sequence[Matrix4], T_camera_board: Sequence[Matrix4]) -> Matrix4:
    """Tsai & Lenz (1989): rotation from modified Rodrigues vectors ``P = 2 sin(theta/2) axis``.

    R_X maps B's axis onto A's; with the Gibbs vector ``x = tan(theta_X / 2) axis_X`` that reads
    ``P_A - P_B = x cross (P_A + P_B)``, i.e. ``skew(P_A + P_B) x = P_B - P_A``, linear in x.
    """
    pairs = motion_pairs(T_base_flange, T_camera_board)
    rows, rhs = [], []
    for A, B in pairs:
        pa, pb = _modified_rodrigues(A), _modified_rodrigues(B)
        rows.append(_skew(pa + pb))
        rhs.append(pb - pa)
    x = np.linalg.lstsq(np.vstack(rows), np.concatenate(rhs), rcond=None)[0]
    norm = float(np.linalg.norm(x))
    rotvec = np.zeros(3) if norm == 0.0 else 2.0 * np.arctan(norm) * x / norm
    return _translation(pairs, Rotation.from_rotvec(rotvec).as_matrix())


def _modified_rodrigues(T: Matrix4) -> NDArray[np.float64]:
    rv = Rotation.from_matrix(T[:3, :3]).as_rotvec()
    theta = float(np.linalg.norm(rv))
    return np.zeros(3) if theta == 0.0 else 2.0 * np.sin(theta / 2.0) * rv / theta


def solve_park(T_base_flange: Sequence[Matrix4], T_camera_board: Sequence[Matrix4]) -> Matrix4:
    """Park & Martin (1994): the log-rotations obey ``alpha_i = R_X beta_i``.

    Their closed form ``(M^T M)^(-1/2) M^T`` with ``M = sum beta alpha^T`` is the orthogonal
    Procrustes fit of the betas onto the alphas, which SciPy's ``align_vectors`` computes.
    """
    pairs = motion_pairs(T_base_flange, T_camera_board)
    alpha = np.array([Rotation.from_matrix(A[:3, :3]).as_rotvec() for A, _ in pairs])
    beta = np.array([Rotation.from_matrix(B[:3, :3]).as_rotvec() for _, B in pairs])
    R_X, _ = Rotation.align_vectors(alpha, beta)
    return _translation(pairs, R_X.as_matrix())


def solve_horaud(T_base_flange: Sequence[Matrix4], T_camera_board: Sequence[Matrix4]) -> Matrix4:
    """Horaud & Dornaika (1995), linear form: ``q_A * q_X = q_X * q_B`` for unit quaternions.

    Each pair gives 4 homogeneous equations ``(L(q_A) - R(q_B)) q_X = 0``; q_X is the right
    singular vector of the stacked system with the smallest singular value.
    """
    pairs = motion_pairs(T_base_flange, T_camera_board)
    blocks = []
    for A, B in pairs:
        qa = _quat_wxyz(A)
        qb = _quat_wxyz(B)
        blocks.append(_quat_left(qa) - _quat_right(qb))
    _, _, Vt = np.linalg.svd(np.vstack(blocks))
    w, x, y, z = Vt[-1]
    return _translation(pairs, Rotation.from_quat([x, y, z, w]).as_matrix())


def _quat_wxyz(T: Matrix4) -> NDArray[np.float64]:
    x, y, z, w = Rotation.from_matrix(T[:3, :3]).as_quat()
    q = np.array([w, x, y, z])
    return q if w >= 0.0 else -q  # A and B share their angle, so both get the same sign


def _quat_left(q: NDArray[np.float64]) -> NDArray[np.float64]:
    """Matrix of ``p -> q * p`` (Hamilton product, w first)."""
    w, x, y, z = q
    return np.array([[w, -x, -y, -z], [x, w, -z, y], [y, z, w, -x], [z, -y, x, w]])


def _quat_right(q: NDArray[np.float64]) -> NDArray[np.float64]:
    """Matrix of ``p -> p * q``."""
    w, x, y, z = q
    return np.array([[w, -x, -y, -z], [x, w, z, -y], [y, -z, w, x], [z, y, -x, w]])


SOLVERS: dict[str, Solver] = {"tsai": solve_tsai, "park": solve_park, "horaud": solve_horaud}


def solve_hand_eye(
    method: str, T_base_flange: Sequence[Matrix4], T_camera_board: Sequence[Matrix4]
) -> Matrix4:
    """``T_flange_camera`` by the named closed-form method (a key of :data:`SOLVERS`)."""
    try:
        solver = SOLVERS[method]
    except KeyError:
        raise HandEyeError(
            f"unknown hand-eye method {method!r}; choose one of {', '.join(SOLVERS)}"
        ) from None
    return solver(T_base_flange, T_camera_board)


@dataclass(frozen=True)
class BoardSpread:
    """ViSP's consistency check: how far each view's ``T_base_board`` is from their mean."""

    T_base_board_mean: Matrix4
    per_view_mm: NDArray[np.float64]
    per_view_deg: NDArray[np.float64]

    @property
    def mean_mm(self) -> float:
        return float(self.per_view_mm.mean())

    @property
    def mean_deg(self) -> float:
        return float(self.per_view_deg.mean())


def board_spread(
    T_base_flange: Sequence[Matrix4], T_camera_board: Sequence[Matrix4], T_flange_camera: Matrix4
) -> BoardSpread:
    """Per view, ``T_base_board_i = T_base_flange_i X T_camera_board_i``; distance to the mean.

    The board never moved, so with perfect data all estimates coincide; the spread is the
    data's own disagreement, in the units a robot user thinks in.
    """
    Ts = [
        np.asarray(Tf, dtype=float) @ T_flange_camera @ np.asarray(Tc, dtype=float)
        for Tf, Tc in zip(T_base_flange, T_camera_board, strict=True)
    ]
    rots = Rotation.from_matrix(np.array([T[:3, :3] for T in Ts]))
    mean_rot = rots.mean()
    t = np.array([T[:3, 3] for T in Ts])
    t_mean = t.mean(axis=0)
    per_mm = np.linalg.norm(t - t_mean, axis=1)
    per_deg = np.degrees((mean_rot.inv() * rots).magnitude())
    return BoardSpread(make_T(mean_rot.as_matrix(), t_mean), per_mm, per_deg)


@dataclass(frozen=True)
class JointResult:
    """Joint refinement of ``T_flange_camera`` and ``T_base_board`` on corner reprojections."""

    T_flange_camera: Matrix4
    T_base_board: Matrix4
    camera: CameraModel  # the input intrinsics, or the refined ones with free_intrinsics
    rms_px: float
    per_view_rms_px: NDArray[np.float64]
    std_position_mm: NDArray[np.float64]  # 1-sigma of T_flange_camera's translation
    std_rotvec_deg: NDArray[np.float64]  # 1-sigma of its rotation vector
    converged: bool


def refine_joint(
    T_base_flange: Sequence[Matrix4],
    image_points_px: Sequence[NDArray[np.float64]],
    object_points_mm: NDArray[np.float64] | Sequence[NDArray[np.float64]],
    camera: CameraModel,
    T_flange_camera: Matrix4,
    T_base_board: Matrix4,
    free_intrinsics: bool = False,
    hold_rotation: bool = False,
) -> JointResult:
    """Levenberg-Marquardt over 12 parameters on the reprojection error of every feature.

    Robot poses and intrinsics are taken as exact: whatever they get wrong shows up in the rms,
    which is why the rms is the honest measure of whether the data agree with themselves.
    With ``free_intrinsics`` fx, fy, cx, cy are refined too (16 parameters): a diagnostic that
    tells whether wrong intrinsics could explain a high rms (then the rms drops a lot).
    ``object_points_mm`` is one (N, 3) array for all views, or one array per view when views
    see different subsets of the target.

    With ``hold_rotation`` the rotation of ``T_flange_camera`` is kept as given (an AX = XB
    answer) and only its translation and ``T_base_board`` are refined (9 parameters). With
    every view pivoting about the target, the mount's roll about the optical axis is the
    images' weak direction (it differs from turning the target about its normal only by the
    views' tilt): flange poses a few tenths of a millimetre off (an arm without kinematic
    calibration) turn the free fit by tenths of a degree about it, while the motions'
    rotations, which position errors do not touch, fix it to a few hundredths.
    """
    flanges = [np.asarray(T, dtype=float) for T in T_base_flange]
    observed = [np.asarray(p, dtype=float).reshape(-1, 2) for p in image_points_px]
    if len(flanges) != len(observed):
        raise HandEyeError(f"{len(flanges)} robot poses but {len(observed)} corner sets")
    if isinstance(object_points_mm, np.ndarray) and object_points_mm.ndim == 2:
        per_view_obj = [object_points_mm] * len(observed)
    else:
        per_view_obj = [np.asarray(o, dtype=float).reshape(-1, 3) for o in object_points_mm]
    obj_h = [np.column_stack((o, np.ones(len(o)))).T for o in per_view_obj]
    if len(obj_h) != len(observed) or any(
        o.shape[1] != len(uv) for o, uv in zip(obj_h, observed, strict=True)
    ):
        raise HandEyeError("object points and image points do not match view by view")

    R_held = np.asarray(T_flange_camera, dtype=float)[:3, :3]
    n_rot = 0 if hold_rotation else 3

    def unpack(p: NDArray[np.float64]) -> tuple[Matrix4, Matrix4, CameraModel]:
        R_X = R_held if hold_rotation else Rotation.from_rotvec(p[0:3]).as_matrix()
        X = make_T(R_X, p[n_rot:n_rot + 3])
        W = make_T(Rotation.from_rotvec(p[n_rot + 3:n_rot + 6]).as_matrix(),
                   p[n_rot + 6:n_rot + 9])
        cam = camera
        if free_intrinsics:
            f = p[n_rot + 9:]
            cam = CameraModel(f[0], f[1], f[2], f[3], camera.dist, camera.width, camera.height)
        return X, W, cam

    def residuals(p: NDArray[np.float64]) -> NDArray[np.float64]:
        X, W, cam = unpack(p)
        out = []
        for Tf, uv, obj in zip(flanges, observed, obj_h, strict=True):
            pc = (invert_T(Tf @ X) @ W @ obj)[:3].T
            out.append((cam.project(pc) - uv).ravel())
        return np.concatenate(out)

    p0 = np.concatenate([
        Rotation.from_matrix(T_flange_camera[:3, :3]).as_rotvec()[:n_rot],
        T_flange_camera[:3, 3],
        Rotation.from_matrix(T_base_board[:3, :3]).as_rotvec(), T_base_board[:3, 3],
    ])
    if free_intrinsics:
        p0 = np.concatenate([p0, [camera.fx, camera.fy, camera.cx, camera.cy]])
    sol = least_squares(residuals, p0, method="lm", x_scale="jac", xtol=1e-15, ftol=1e-15,
                        gtol=1e-15, max_nfev=200 * len(p0))
    X, W, cam = unpack(sol.x)
    err = np.linalg.norm(sol.fun.reshape(-1, 2), axis=1)
    splits = np.cumsum([len(uv) for uv in observed])[:-1]
    per_view = np.array([np.sqrt(np.mean(e**2)) for e in np.split(err, splits)])
    sigma2 = float(np.sum(sol.fun**2)) / max(sol.fun.size - len(p0), 1)
    try:
        std = np.sqrt(np.clip(np.diag(np.linalg.inv(sol.jac.T @ sol.jac)) * sigma2, 0.0, None))
    except np.linalg.LinAlgError:
        std = np.full(len(p0), np.inf)
    std_rot = std[0:3] if n_rot else np.zeros(3)
    return JointResult(
        T_flange_camera=X, T_base_board=W, camera=cam, rms_px=float(np.sqrt(np.mean(err**2))),
        per_view_rms_px=per_view, std_position_mm=std[n_rot:n_rot + 3],
        std_rotvec_deg=np.degrees(std_rot),
        converged=bool(sol.status > 0),
    )
