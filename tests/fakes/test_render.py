"""The scene renderer: exact perspective of each dot, determinism, robustness to odd poses."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from estimator import CameraModel, Target
from estimator.transforms import make_T
from fakes.render import (
    _Disc,
    _Scene,
    ellipse_centre_px,
    random_pose,
    random_scene,
    random_target,
    render_target,
    render_target_full_frame,
)

CAM = CameraModel(800.0, 800.0, 639.5, 399.5, (), 1280, 800)
ONE_DOT_SET = Target([[0, 0, 0], [60, 0, 0], [0, 40, 0], [70, 50, 0]], 20.0)


def _tilted(deg: float, z_mm: float = 300.0) -> np.ndarray:
    R = Rotation.from_rotvec([np.radians(deg), 0.0, 0.0]).as_matrix()
    return make_T(R, [-30.0, -20.0, z_mm])


def _clean(target: Target, T: np.ndarray, **kw: object) -> np.ndarray:
    return render_target(CAM, target, T, blur_sigma_px=0.0, noise_std=0.0,  # type: ignore[arg-type]
                         lighting_gradient=0.0, rng=np.random.default_rng(0), **kw)


def test_dot_is_the_exact_perspective_ellipse() -> None:
    """Darkness-weighted centre and area of a rendered dot match the analytic imaged circle,
    whose centre is measurably not the projection of the circle's centre."""
    T = _tilted(55.0, 250.0)
    img = _clean(ONE_DOT_SET, T).astype(float)
    plate, dot = 205.0, 40.0
    centre = ellipse_centre_px(CAM, T, ONE_DOT_SET.points_mm[0], 10.0)
    projected = CAM.project(ONE_DOT_SET.points_mm[:1] @ T[:3, :3].T + T[:3, 3])[0]
    u0, v0 = np.round(centre).astype(int)
    win = img[v0 - 45: v0 + 46, u0 - 45: u0 + 46]
    w = np.clip((plate - win) / (plate - dot), 0.0, 1.0)
    ys, xs = np.indices(win.shape)
    got = np.array([(w * xs).sum() / w.sum() + u0 - 45, (w * ys).sum() / w.sum() + v0 - 45])
    assert np.linalg.norm(got - centre) < 0.02
    assert np.linalg.norm(projected - centre) > 0.1  # the perspective bias is really there
    # The dot's area (its total darkness) agrees with a 64x-supersampled reference render.
    fine = render_target(CAM, ONE_DOT_SET, T, blur_sigma_px=0.0, noise_std=0.0,
                         lighting_gradient=0.0, supersample=8, rng=np.random.default_rng(0))
    wf = np.clip((plate - fine[v0 - 45: v0 + 46, u0 - 45: u0 + 46].astype(float))
                 / (plate - dot), 0.0, 1.0)
    assert abs(w.sum() - wf.sum()) < 0.01 * wf.sum()


def test_same_rng_same_image_and_uint8_frame() -> None:
    T = _tilted(20.0)
    a = render_target(CAM, ONE_DOT_SET, T, rng=np.random.default_rng(5), clutter=2, frame=True)
    b = render_target(CAM, ONE_DOT_SET, T, rng=np.random.default_rng(5), clutter=2, frame=True)
    assert a.dtype == np.uint8 and a.shape == (800, 1280)
    assert np.array_equal(a, b)


def test_distortion_moves_dots_where_the_lens_model_says() -> None:
    cam = CameraModel(800.0, 800.0, 639.5, 399.5, (-0.25, 0.08, 0.0, 0.0, 0.0), 1280, 800)
    T = make_T(np.eye(3), [-250.0, -150.0, 400.0])
    img = render_target(cam, ONE_DOT_SET, T, blur_sigma_px=0.0, noise_std=0.0,
                        lighting_gradient=0.0, rng=np.random.default_rng(0)).astype(float)
    ideal = ellipse_centre_px(CAM, T, ONE_DOT_SET.points_mm[0], 10.0)
    expected = cam.distort_points(((ideal - [639.5, 399.5]) / 800.0)[None])[0]
    assert np.linalg.norm(expected - ideal) > 5.0  # strong enough to matter
    u0, v0 = np.round(expected).astype(int)
    win = img[v0 - 30: v0 + 31, u0 - 30: u0 + 31]
    w = np.clip((205.0 - win) / 165.0, 0.0, 1.0)
    ys, xs = np.indices(win.shape)
    got = np.array([(w * xs).sum() / w.sum() + u0 - 30, (w * ys).sum() / w.sum() + v0 - 30])
    assert np.linalg.norm(got - expected) < 0.3  # distortion is not affine across a dot


def test_light_polarity_and_non_planar_targets_render() -> None:
    rng = np.random.default_rng(2)
    light = Target(ONE_DOT_SET.points_mm, 20.0, "light")
    img = _clean(light, _tilted(10.0))
    c = np.round(ellipse_centre_px(CAM, _tilted(10.0), light.points_mm[0], 10.0)).astype(int)
    assert img[c[1], c[0]] > 200 and img[c[1] + 40, c[0] + 40] < 80
    s = random_scene(rng, CAM, n_dots=7, planar=False)
    assert not s.target.is_planar and s.image.shape == (800, 1280)


def test_target_partly_behind_the_camera_does_not_crash() -> None:
    T = make_T(Rotation.from_rotvec([np.radians(89.0), 0, 0]).as_matrix(), [0.0, 0.0, 5.0])
    img = render_target(CAM, ONE_DOT_SET, T, rng=np.random.default_rng(0))
    assert img.shape == (800, 1280)


@pytest.mark.parametrize("planar", [True, False])
def test_random_pose_keeps_every_dot_in_view(planar: bool) -> None:
    rng = np.random.default_rng(3)
    for _ in range(20):
        tgt = random_target(rng, 8, planar=planar)
        T = random_pose(rng, CAM, tgt)
        px = CAM.project(tgt.points_mm @ T[:3, :3].T + T[:3, 3])
        assert (px >= 40).all() and (px[:, 0] <= 1239).all() and (px[:, 1] <= 759).all()


@pytest.mark.parametrize("case", [
    {"T": _tilted(30.0)},  # drawn box well inside the frame
    {"T": _tilted(20.0, 90.0), "clutter": 2},  # the plate fills the frame
    {"T": make_T(np.eye(3), [-120.0, -80.0, 300.0]), "frame": True, "blur_sigma_px": 1.5},
    {"T": make_T(np.eye(3), [-520.0, -300.0, 300.0]), "lighting_gradient": 0.0},  # at a corner
    {"T": _tilted(45.0, 400.0), "noise_std": 0.0, "distorted": True},
    {"T": make_T(np.eye(3), [0.0, 0.0, -300.0])},  # behind the camera: nothing drawn
])
def test_fast_render_is_the_full_frame_computation(case: dict[str, object]) -> None:
    """The render that works only around what is drawn gives the straightforward full-frame
    image (same seed) within one grey level, and only rarely off by one (float rounding)."""
    kw = dict(case)
    T = kw.pop("T")
    cam = CameraModel(400.0, 400.0, 319.5, 199.5,
                      (-0.2, 0.05, 0.001, 0.0, 0.0) if kw.pop("distorted", False) else (),
                      640, 400)
    fast = render_target(cam, ONE_DOT_SET, T, rng=np.random.default_rng(7),  # type: ignore[arg-type]
                         **kw)
    full = render_target_full_frame(cam, ONE_DOT_SET, T,  # type: ignore[arg-type]
                                    rng=np.random.default_rng(7), **kw)
    diff = np.abs(fast.astype(int) - full)
    assert diff.max() <= 1
    assert diff.mean() < 2e-3
    assert full.std() > 0.5 or kw.get("noise_std") == 0.0  # a real image, not an empty one


def test_a_dots_centre_follows_the_pose_continuously() -> None:
    """Moved by a thousandth of a pixel at a time, a dot's imaged centre moves with it: a
    sample's coverage ramps across the rim, so the centre does not stand still between the
    samples the rim crosses (as a 4 x 4 grid of in-or-out samples made it, a pattern fixed
    to the pose that no averaging of frames removes)."""
    step_px = 0.001
    centres = []
    for k in range(40):
        T = make_T(np.eye(3), [k * step_px * 450.0 / CAM.fx, 0.0, 450.0])
        got = _Scene(CAM, T, distort=False).disc_coverage(_Disc(np.zeros(3), 4.0), 4)
        assert got is not None
        x0, _, cov = got
        cols = x0 + np.arange(cov.shape[1])
        centres.append(float((cov.sum(axis=0) * cols).sum() / cov.sum()))
    moved = np.diff(centres)
    assert np.all(moved > 0.2 * step_px)  # it moves at every step
    assert abs(float(np.mean(moved)) - step_px) < 0.1 * step_px
