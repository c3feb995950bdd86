"""Matching blobs to dots: clutter, a missing dot, symmetric targets, and honest failures."""

from __future__ import annotations

import numpy as np
import pytest

from estimator import CameraModel, CorrespondenceError, Target, TooFewBlobsError
from estimator.correspondence import match_blobs
from estimator.solve import solve_pose_near
from estimator.transforms import pose_distance
from fakes.render import random_pose, random_target

CAM = CameraModel(800.0, 800.0, 639.5, 399.5, (), 1280, 800)
SIM_TARGET = Target([[0, 0, 0], [60, 0, 0], [100, 10, 0], [0, 50, 0], [40, 70, 0],
                     [90, 60, 0]], 10.0)


def _image_points(target: Target, T: np.ndarray, rng: np.random.Generator,
                  noise_px: float = 0.1) -> np.ndarray:
    px = CAM.project(target.points_mm @ T[:3, :3].T + T[:3, 3])
    return px + rng.normal(0.0, noise_px, px.shape)


def _clutter_near(px: np.ndarray, count: int, rng: np.random.Generator) -> np.ndarray:
    """Dot-like extra blobs inside the target's image region, away from the real dots."""
    lo, hi = px.min(axis=0) - 20, px.max(axis=0) + 20
    out: list[np.ndarray] = []
    while len(out) < count:
        c = rng.uniform(lo, hi)
        if np.linalg.norm(px - c, axis=1).min() > 25 and all(
                np.linalg.norm(c - o) > 25 for o in out):
            out.append(c)
    return np.array(out)


def _check(target: Target, T: np.ndarray, result, blobs_px: np.ndarray,
           order: np.ndarray) -> None:
    """Every matched blob is the right dot and the pose is right."""
    for mid, bi in zip(result.model_ids, result.blob_indices, strict=True):
        assert order[bi] == mid
    dt, dr = pose_distance(result.pose.T_camera_target, T)
    assert dt < 3.0 and dr < 2.0  # small 4-dot targets far away are imprecise, not wrong


@pytest.mark.parametrize("planar", [True, False])
def test_exact_and_shuffled(planar: bool) -> None:
    rng = np.random.default_rng(0)
    for _ in range(15):
        target = random_target(rng, int(rng.integers(4, 13)), planar=planar)
        T = random_pose(rng, CAM, target)
        px = _image_points(target, T, rng)
        perm = rng.permutation(len(px))
        result = match_blobs(px[perm], target, CAM)
        assert len(result.model_ids) == target.n_points and not result.ambiguous
        _check(target, T, result, px[perm], perm)


@pytest.mark.parametrize("planar", [True, False])
def test_three_clutter_blobs_and_one_missing_dot(planar: bool) -> None:
    rng = np.random.default_rng(1)
    for trial in range(12):
        missing = trial % 2 == 1
        # With one of 5 dots missing, 4 remain: 4 points fit almost any 4 blobs of a plate, so
        # clutter + missing needs 6+ dots to be decidable (see the next test for 5).
        target = random_target(rng, int(rng.integers(6 if missing else 5, 9)), planar=planar)
        T = random_pose(rng, CAM, target)
        px = _image_points(target, T, rng)
        order = np.arange(len(px))
        if missing:
            drop = int(rng.integers(len(px)))
            px, order = np.delete(px, drop, axis=0), np.delete(order, drop)
        blobs = np.vstack((px, _clutter_near(px, 3, rng)))
        order = np.concatenate((order, [-1, -1, -1]))
        perm = rng.permutation(len(blobs))
        result = match_blobs(blobs[perm], target, CAM)
        assert len(result.model_ids) == target.n_points - missing
        assert not result.ambiguous
        _check(target, T, result, blobs[perm], order[perm])


def test_undecidable_views_are_ambiguous_never_confidently_wrong() -> None:
    """5 dots, one missing, 3 clutter blobs: either the right answer or `ambiguous`."""
    rng = np.random.default_rng(5)
    decided = 0
    for _ in range(15):
        target = random_target(rng, 5)
        T = random_pose(rng, CAM, target)
        px = _image_points(target, T, rng)
        drop = int(rng.integers(5))
        px, order = np.delete(px, drop, axis=0), np.delete(np.arange(5), drop)
        blobs = np.vstack((px, _clutter_near(px, 3, rng)))
        order = np.concatenate((order, [-1, -1, -1]))
        try:
            result = match_blobs(blobs, target, CAM)
        except CorrespondenceError:
            continue
        if not result.ambiguous:
            decided += 1
            _check(target, T, result, blobs, order)
    print(f"decided {decided}/15 views with 4 of 5 dots among 3 clutter blobs")


@pytest.mark.parametrize("points", [
    [[0, 0, 0], [50, 0, 0], [50, 50, 0], [0, 50, 0]],  # square: 4-fold
    [[0, 0, 0], [40, 0, 0], [80, 0, 0], [0, 40, 0], [40, 40, 0], [80, 40, 0]],  # 2x3 grid
])
def test_symmetric_target_is_reported_ambiguous(points: list[list[float]]) -> None:
    rng = np.random.default_rng(2)
    target = Target(points, 8.0)
    for _ in range(4):  # random spins: the kept labelling is the solved one or derived
        T = random_pose(rng, CAM, target, max_tilt_deg=10.0)
        result = match_blobs(_image_points(target, T, rng, 0.05), target, CAM)
        assert result.ambiguous and result.n_equivalent >= 2
        assert result.pose.ambiguous and result.pose.identity == "symmetry"
        assert any("symmetric" in note for note in result.pose.notes)
        # The kept labelling's pose is derived (T S), not re-solved: it is the pose a solve
        # of that labelling gives, residuals and covariance included.
        ids = list(result.model_ids)
        pts = result.pose.image_points_px
        assert pts is not None
        again = solve_pose_near(target.points_mm[ids], pts, CAM, result.pose.T_camera_target)
        dt, dr = pose_distance(again.T_camera_target, result.pose.T_camera_target)
        assert dt < 1e-3 and dr < 1e-4
        assert np.allclose(again.residuals_px, result.pose.residuals_px, atol=1e-4)
        assert result.pose.covariance is not None and again.covariance is not None
        assert np.allclose(again.covariance, result.pose.covariance, rtol=1e-2, atol=1e-9)
        for eq in result.pose.equivalent_poses:
            assert abs(eq.rms_px - result.pose.rms_px) < 1e-12
        # The smallest rotation of the equivalent poses was kept.
        angle = _angle_deg(result.pose.T_camera_target)
        assert all(angle <= _angle_deg(e.T_camera_target) + 1e-9
                   for e in result.pose.equivalent_poses)


def _angle_deg(T: np.ndarray) -> float:
    return float(np.degrees(np.arccos(np.clip((np.trace(T[:3, :3]) - 1) / 2, -1, 1))))


def test_inconsistent_blobs_raise_correspondence_error() -> None:
    rng = np.random.default_rng(3)
    T = random_pose(rng, CAM, SIM_TARGET)
    # Right number of blobs, wrong geometry: a different target's dots.
    other = random_target(rng, 6)
    px = _image_points(other, random_pose(rng, CAM, other), rng)
    with pytest.raises(CorrespondenceError, match="target"):
        match_blobs(px, SIM_TARGET, CAM)
    # Collinear blobs cannot be the dots of a plate either.
    line = np.column_stack((np.linspace(100, 900, 6), np.full(6, 400.0)))
    with pytest.raises(CorrespondenceError):
        match_blobs(line, SIM_TARGET, CAM)
    assert T is not None


def test_too_few_blobs_says_how_many() -> None:
    with pytest.raises(TooFewBlobsError) as err:
        match_blobs(np.array([[1.0, 2.0], [300.0, 5.0], [40.0, 90.0]]), SIM_TARGET, CAM)
    assert err.value.found == 3 and err.value.needed == 5
    assert "found 3 blob(s)" in err.value.message
    with pytest.raises(TooFewBlobsError):
        match_blobs(np.zeros((5, 2)), SIM_TARGET, CAM, max_missing=0)


def test_three_collinear_dots_and_a_fourth_are_matched() -> None:
    target = Target([[0, 0, 0], [50, 0, 0], [100, 0, 0], [40, 70, 0]], 8.0)
    rng = np.random.default_rng(51)
    for _ in range(10):
        T = random_pose(rng, CAM, target)
        px = _image_points(target, T, rng)
        perm = rng.permutation(len(px))
        result = match_blobs(px[perm], target, CAM)
        assert len(result.model_ids) == 4
        _check(target, T, result, px[perm], perm)


def test_a_6x6_grid_is_matched_up_to_its_symmetry() -> None:
    from cell.bench.estimator import _error_mod_symmetry
    from fakes.render import grid_target

    target = grid_target(6, 6, 25.0, 7.0)
    rng = np.random.default_rng(52)
    for _ in range(5):
        T = random_pose(rng, CAM, target, max_tilt_deg=40.0)
        px = _image_points(target, T, rng)
        result = match_blobs(px[rng.permutation(len(px))], target, CAM)
        assert len(result.model_ids) == 36
        assert result.ambiguous and len(result.pose.equivalent_poses) == 3
        t_err, r_err = _error_mod_symmetry(result.pose.T_camera_target, T, target)
        assert t_err < 2.0 and r_err < 0.5


def test_layouts_that_cannot_fix_a_pose_are_refused() -> None:
    from cell.config.schema import TargetConfig

    line = [[0.0, 0.0, 0.0], [50.0, 0.0, 0.0], [100.0, 0.0, 0.0], [150.0, 0.0, 0.0]]
    with pytest.raises(ValueError, match="one line"):
        Target(line, 5.0)
    with pytest.raises(ValueError, match="one line"):
        TargetConfig(points_mm=line, dot_diameter_mm=5.0)  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="distinct"):
        Target([[0, 0, 0]] * 3 + [[10, 0, 0], [0, 10, 0]], 5.0)
    with pytest.raises(ValueError, match="4 to 100"):
        Target(np.zeros((101, 3)), 5.0)
    far = [[0.0, 0.0, 0.0], [1e308, 0.0, 0.0], [0.0, -1e308, 0.0], [1.0, 1.0, 0.0]]
    with np.errstate(all="raise"), pytest.raises(ValueError, match="within"):
        Target(far, 5.0)  # refused before any arithmetic overflows
    with pytest.raises(ValueError, match="within"):
        TargetConfig(points_mm=far, dot_diameter_mm=5.0)  # type: ignore[arg-type]


def _asymmetric_grid(rows: int = 4, cols: int = 11, pitch_mm: float = 40.0) -> Target:
    """OpenCV's asymmetric circle grid layout: every other column shifted by half a pitch."""
    pts = [[(2 * j + i % 2) * pitch_mm / 2, i * pitch_mm / 2, 0.0]
           for j in range(rows) for i in range(cols)]
    return Target(pts, 5.0)


@pytest.mark.parametrize(("name", "n_equivalent"), [
    ("grid10x10", 4), ("asymmetric4x11", 1), ("line4_plus1", 1), ("cross5", 4)])
def test_layouts_from_4_to_100_dots(name: str, n_equivalent: int) -> None:
    """Grids up to 100 dots, an asymmetric circle grid, four dots on a line plus one, a
    4-fold cross: every dot matched, the pose right up to the layout's symmetry, which the
    result reports as the number of equivalent labellings."""
    from cell.bench.estimator import _error_mod_symmetry
    from fakes.render import grid_target

    target = {
        "grid10x10": grid_target(10, 10, 15.0, 5.0),
        "asymmetric4x11": _asymmetric_grid(),
        "line4_plus1": Target([[0, 0, 0], [30, 0, 0], [60, 0, 0], [90, 0, 0], [45, 50, 0]], 8.0),
        "cross5": Target([[0, 0, 0], [50, 0, 0], [-50, 0, 0], [0, 50, 0], [0, -50, 0]], 8.0),
    }[name]
    rng = np.random.default_rng(53)
    for _ in range(6):
        T = random_pose(rng, CAM, target, max_tilt_deg=40.0, distance_mm=(350.0, 500.0))
        px = _image_points(target, T, rng)
        perm = rng.permutation(len(px))
        result = match_blobs(px[perm], target, CAM)
        assert len(result.model_ids) == target.n_points
        assert result.n_equivalent == n_equivalent
        assert len(result.pose.equivalent_poses) == n_equivalent - 1
        t_err, r_err = _error_mod_symmetry(result.pose.T_camera_target, T, target)
        assert t_err < 5.0 and r_err < 1.0, (t_err, r_err)
