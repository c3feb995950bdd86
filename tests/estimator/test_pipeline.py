"""The full image -> pose pipeline on rendered frames: accuracy, tracking, typed failures."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from estimator import (
    CameraModel,
    CorrespondenceError,
    Estimator,
    Target,
    TooFewBlobsError,
)
from estimator.transforms import make_T, pose_distance
from fakes.render import random_pose, random_scene, random_target, render_target

CAM = CameraModel(800.0, 800.0, 639.5, 399.5, (), 1280, 800)
CAM_DIST = CameraModel(800.0, 800.0, 639.5, 399.5, (-0.12, 0.05, 0.0, 0.0, 0.0), 1280, 800)


@pytest.mark.parametrize(("camera", "planar", "clutter"), [
    (CAM, True, 0), (CAM_DIST, True, 0), (CAM, True, 3), (CAM, False, 0),
])
def test_pose_matches_ground_truth_on_rendered_frames(
    camera: CameraModel, planar: bool, clutter: int
) -> None:
    rng = np.random.default_rng(20 + clutter + 2 * planar)
    t_err, r_err = [], []
    for _ in range(10):
        s = random_scene(rng, camera, n_dots=int(rng.integers(6, 9)), planar=planar,
                         clutter=clutter)
        result = Estimator(camera, s.target).estimate(s.image)
        assert len(result.matched_ids) == s.target.n_points and not result.ambiguous
        assert len(result.matched_blobs) == len(result.matched_ids)
        assert result.image_points_px is not None and len(result.image_points_px) == len(
            result.matched_ids)
        dt, dr = pose_distance(result.T_camera_target, s.T_camera_target)
        t_err.append(dt)
        r_err.append(dr)
        assert result.rms_px < 0.3
    # 8 mm dots at 350-700 mm, 1.5 grey levels of noise: tenths of a mm, hundredths of a deg.
    assert np.median(t_err) < 0.3 and max(t_err) < 1.5, t_err
    assert np.median(r_err) < 0.1 and max(r_err) < 0.5, r_err


def test_frame_around_the_dots_does_not_disturb_the_pose() -> None:
    rng = np.random.default_rng(30)
    s = random_scene(rng, CAM, n_dots=6, frame=True)
    result = Estimator(CAM, s.target).estimate(s.image)
    assert pose_distance(result.T_camera_target, s.T_camera_target)[0] < 1.0


@pytest.mark.parametrize("threshold", [120.0, None])
def test_tracking_gives_the_full_search_result_and_follows_motion(
    threshold: float | None,
) -> None:
    """With one fixed threshold the windows see exactly the full search's regions, so the
    centres are identical; with Otsu, the full search re-thresholds every frame and the
    centres move by a few thousandths of a pixel at most.

    The poses agree to 1e-3 mm / 1e-3 deg, not exactly: a tracked frame corrects its points
    with the perspective-bias offsets of the previous frame's pose and refines once, where the
    full search refines, computes the offsets at that raw pose and refines again. Offsets of
    up to 0.08 px differ by up to ~2e-3 px between the two evaluation poses, which moves the
    pose by up to ~6e-4 mm (measured over 15 targets at 300-700 mm moving 2.7 mm and 0.2 deg
    per frame); the 1e-3 tolerance is still 30x below the noise-induced error (~0.03 mm)."""
    rng = np.random.default_rng(31)
    target = random_target(rng, 7)
    T = random_pose(rng, CAM, target, distance_mm=(400.0, 500.0))
    tracker = Estimator(CAM, target, threshold=threshold)
    full = Estimator(CAM, target, tracking=False, threshold=threshold)
    atol_px = 1e-9 if threshold is not None else 0.01
    tol_mm, tol_deg = (1e-3, 1e-3) if threshold is not None else (0.02, 0.01)
    for k in range(6):
        step = make_T(Rotation.from_rotvec([0.0, 0.003 * k, 0.0]).as_matrix(), [1.5 * k, 0, 0])
        image = render_target(CAM, target, T @ step, rng=rng)
        a, b = tracker.estimate(image), full.estimate(image)
        assert tracker.last_mode == ("full" if k == 0 else "tracking")
        assert full.last_mode == "full"
        assert a.matched_ids == b.matched_ids
        assert np.allclose([(x.u, x.v) for x in a.matched_blobs],
                           [(x.u, x.v) for x in b.matched_blobs], atol=atol_px, rtol=0.0)
        dt, dr = pose_distance(a.T_camera_target, b.T_camera_target)
        assert dt < tol_mm and dr < tol_deg
        assert pose_distance(a.T_camera_target, T @ step)[0] < 1.0


def test_tracking_falls_back_to_full_search_when_the_target_jumps() -> None:
    rng = np.random.default_rng(32)
    target = random_target(rng, 6)
    est = Estimator(CAM, target)
    s1 = render_target(CAM, target, random_pose(rng, CAM, target), rng=rng)
    est.estimate(s1)
    T2 = random_pose(rng, CAM, target)
    result = est.estimate(render_target(CAM, target, T2, rng=rng))
    assert est.last_mode == "full"
    assert pose_distance(result.T_camera_target, T2)[0] < 1.0
    est.reset()
    est.estimate(render_target(CAM, target, T2, rng=rng))
    assert est.last_mode == "full"


def test_empty_frame_says_how_many_blobs_were_found() -> None:
    target = Target([[0, 0, 0], [60, 0, 0], [100, 10, 0], [0, 50, 0], [40, 70, 0],
                     [90, 60, 0]], 10.0)
    blank = np.full((800, 1280), 180, np.uint8)
    with pytest.raises(TooFewBlobsError) as err:
        Estimator(CAM, target).estimate(blank)
    assert err.value.found == 0 and err.value.needed == 5
    assert err.value.code == "too_few_blobs" and "in view" in err.value.message


def test_wrong_target_model_is_a_correspondence_error() -> None:
    rng = np.random.default_rng(33)
    s = random_scene(rng, CAM, n_dots=6)
    other = random_target(np.random.default_rng(99), 6)
    with pytest.raises(CorrespondenceError) as err:
        Estimator(CAM, other).estimate(s.image)
    assert err.value.code == "no_correspondence"


def test_light_dots_and_bad_arguments() -> None:
    rng = np.random.default_rng(34)
    target = random_target(rng, 6, polarity="light")
    T = random_pose(rng, CAM, target)
    result = Estimator(CAM, target).estimate(render_target(CAM, target, T, rng=rng))
    assert pose_distance(result.T_camera_target, T)[0] < 1.0
    with pytest.raises(ValueError, match="8-bit grey"):
        Estimator(CAM, target).estimate(np.zeros((800, 1280), np.float64))  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="unknown detector option"):
        Estimator(CAM, target, min_aera_px=3)
    with pytest.raises(ValueError, match="threshold"):
        Estimator(CAM, target, threshold="magic")


def test_close_range_tilted_frames_end_in_the_true_minimum() -> None:
    """Close range and strong tilt, where POSIT's seed often lands in the wrong one of the two
    planar minima: the full search must still return the true one (a candidate refined only
    roughly once passed for a distinct minimum and stopped the search: 55 mm off with this
    seed)."""
    rng = np.random.default_rng(44)
    errors = []
    for _ in range(60):
        target = random_target(rng, int(rng.integers(5, 9)))
        T = random_pose(rng, CAM, target, distance_mm=(250.0, 400.0), max_tilt_deg=50.0)
        result = Estimator(CAM, target, tracking=False).estimate(
            render_target(CAM, target, T, rng=rng))
        errors.append(pose_distance(result.T_camera_target, T))
    worst_mm, worst_deg = np.max(errors, axis=0)
    assert worst_mm < 0.5 and worst_deg < 0.5, (worst_mm, worst_deg)


def test_symmetric_target_is_tracked_without_label_flips() -> None:
    """A 2-fold symmetric plate: the fresh search says ambiguous with the equivalent pose;
    then every frame is tracked, identities kept by continuity, and no pose jumps."""
    from cell.bench.estimator import _error_mod_symmetry, _rotation_deg, _sequence_pose
    from fakes.render import symmetric_target

    cam = CameraModel(800.0, 800.0, 639.5, 399.5, (), 1280, 800)
    target = symmetric_target()
    est = Estimator(cam, target)
    rng = np.random.default_rng(41)
    T_prev = None
    for k in range(25):
        T = _sequence_pose(k, target)
        result = est.estimate(render_target(cam, target, T, rng=rng))
        if k == 0:
            assert result.ambiguous and len(result.equivalent_poses) == 1
            assert result.identity == "symmetry"
        else:
            assert est.last_mode == "tracking" and result.identity == "continuity"
            assert T_prev is not None and _rotation_deg(T_prev, result.T_camera_target) < 10.0
        t_err, r_err = _error_mod_symmetry(result.T_camera_target, T, target)
        assert t_err < 1.0 and r_err < 0.5
        T_prev = result.T_camera_target
    # A lost track is re-acquired with the labelling nearest the last pose.
    est._tracker.reset()
    result = est.estimate(render_target(cam, target, _sequence_pose(25, target), rng=rng))
    assert est.last_mode == "full" and result.identity == "continuity" and T_prev is not None
    assert not result.ambiguous and _rotation_deg(T_prev, result.T_camera_target) < 10.0


def test_oblique_dots_up_to_70_degrees_are_found() -> None:
    from estimator.blobs import detect_dots
    from fakes.render import ellipse_centre_px, random_pose, random_target

    cam = CameraModel(800.0, 800.0, 639.5, 399.5, (), 1280, 800)
    rng = np.random.default_rng(42)
    found = visible = 0
    for _ in range(8):
        target = random_target(rng, 6)
        T = random_pose(rng, cam, target, min_tilt_deg=60.0, max_tilt_deg=70.0)
        img = render_target(cam, target, T, rng=rng)
        truth = np.array([ellipse_centre_px(cam, T, p, 4.0) for p in target.points_mm])
        centres = detect_dots(img)[0].centres_px
        d = np.linalg.norm(truth[:, None] - centres[None], axis=2).min(axis=1)
        found += int((d < 0.5).sum())
        visible += len(truth)
    assert found == visible


def test_frontal_sim_target_is_not_ambiguous_and_says_why() -> None:
    """The built-in sim target seen head-on: the other coplanar branch is the same answer
    (< 1 mm / 1 deg at the dots) or separable at the measured noise -- never `ambiguous`."""
    from cell.config.schema import load_config

    cfg = load_config()
    target, cam = cfg.target.model(), cfg.camera.model()
    rng = np.random.default_rng(61)
    centre = target.points_mm.mean(axis=0)
    for _ in range(5):
        T = make_T(np.eye(3), np.array([*rng.normal(0.0, 10.0, 2), 350.0]) - centre)
        result = Estimator(cam, target).estimate(render_target(cam, target, T, rng=rng))
        assert not result.ambiguous and result.ambiguity is not None
        assert not result.ambiguity.different or result.ambiguity.margin > 1.0
        assert result.identity == "unique"
    # Settings that make every pose "different" are refused.
    with pytest.raises(ValueError, match="positive"):
        Estimator(cam, target, ambiguity_mm=0.0)


def test_window_search_gives_the_full_search_pose_and_falls_back_outside_it() -> None:
    """A window around the dots finds exactly the whole frame's dots (same threshold, same
    regions), with a dot hidden too; a window that misses the plate, or cuts a dot, falls
    back to the whole frame."""
    from estimator.window import search_window

    rng = np.random.default_rng(41)
    s = random_scene(rng, CAM, n_dots=6)
    full = Estimator(CAM, s.target, tracking=False)
    seen = full.estimate(s.image)
    assert seen.image_points_px is not None
    r = int(np.ceil(max(b.major_axis_px for b in seen.matched_blobs)))
    hidden = s.image.copy()  # the tool over one dot
    u, v = np.round(seen.image_points_px[0]).astype(int)
    hidden[v - r:v + r + 1, u - r:u + r + 1] = 70
    window = search_window(seen.image_points_px, 2.0 * r, CAM.width, CAM.height)
    assert window is not None
    for frame in (s.image, hidden):
        searcher = Estimator(CAM, s.target, tracking=False)
        searcher.estimate(s.image)
        want = Estimator(CAM, s.target, tracking=False).estimate(frame)
        got = searcher.estimate(frame, window)
        assert searcher.last_mode == "window"
        assert got.matched_ids == want.matched_ids
        assert np.array_equal(got.T_camera_target, want.T_camera_target)
    # a window cutting through the dots: a dot is missing there but not in the frame
    x0, y0, _, y1 = window
    cut = (x0, y0, int(seen.image_points_px[:, 0].max()), y1)
    searcher = Estimator(CAM, s.target, tracking=False)
    got = searcher.estimate(s.image, cut)
    assert searcher.last_mode == "full" and len(got.matched_ids) == 6
    # an empty corner: nothing there, the whole frame is searched
    got = searcher.estimate(s.image, (0, 0, 40, 40))
    assert searcher.last_mode == "full" and len(got.matched_ids) == 6
