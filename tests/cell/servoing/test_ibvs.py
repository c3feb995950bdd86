"""The IBVS law against known geometry: the interaction matrix against the numerical
derivative of projected points, the twist mapping against rigid-body motion, and closed loops
(kinematic, no arm) from translated and rotated views converging on the desired view."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from cell.servoing.ibvs import (
    AdaptiveGain,
    Features,
    LatencyCappedGain,
    base_tcp_twist,
    camera_twist,
    camera_twist_from_base,
    depths_mm,
    features_from_view,
    image_error_px,
    interaction_matrix,
    limit_twist,
    predicted,
    project_normalised,
    remaining_motion,
)
from cell.servoing.ibvs_settle import mean_features, settle_step, step_goal, step_size
from estimator import CameraModel
from estimator.transforms import T_from_pose, invert_T, pose_distance

DOTS = np.array([[0, 0, 0], [60, 0, 0], [100, 10, 0], [0, 50, 0], [40, 70, 0], [90, 60, 0.0]])
T_DESIRED = T_from_pose([-50.0, -35.0, 300.0], [0.05, -0.03, 0.2])  # T_camera_target


def _features(T_camera_target: np.ndarray, ids: tuple[int, ...] = tuple(range(6))) -> Features:
    P = DOTS[list(ids)]
    return Features(ids, project_normalised(T_camera_target, P), depths_mm(T_camera_target, P))


def _move_camera(T_camera_target: np.ndarray, twist: np.ndarray, dt: float) -> np.ndarray:
    """The target seen from a camera that moved at ``twist`` (its own frame) for ``dt``."""
    T_old_new = T_from_pose(twist[:3] * dt, twist[3:] * dt)
    return invert_T(T_old_new) @ T_camera_target


def test_interaction_matrix_is_the_derivative_of_the_projections() -> None:
    f0 = _features(T_DESIRED)
    L = interaction_matrix(f0.xy, f0.depth_mm)
    rng = np.random.default_rng(1)
    for _ in range(5):
        twist = rng.normal(size=6) * np.r_[50.0, 50.0, 50.0, 0.3, 0.3, 0.3]
        dt = 1e-5
        f1 = _features(_move_camera(T_DESIRED, twist, dt))
        numeric = (f1.xy - f0.xy).reshape(-1) / dt
        assert np.allclose(L @ twist, numeric, rtol=1e-3, atol=1e-6)


def test_base_twist_moves_the_tcp_and_the_camera_as_one_body() -> None:
    T_base_tcp = T_from_pose([-400.0, 100.0, 300.0], [3.0, 0.2, -0.1])
    T_tcp_camera = T_from_pose([0.0, 60.0, -120.0], [0.01, 0.02, 0.0])
    T_base_camera = T_base_tcp @ T_tcp_camera
    v_c = np.array([10.0, -20.0, 5.0, 0.1, -0.2, 0.3])
    tw = base_tcp_twist(v_c, T_base_camera, T_base_tcp)
    assert np.allclose(camera_twist_from_base(tw, T_base_camera, T_base_tcp), v_c)
    dt = 1e-5
    T_tcp_next = np.eye(4)
    T_tcp_next[:3, :3] = Rotation.from_rotvec(tw[3:] * dt).as_matrix() @ T_base_tcp[:3, :3]
    T_tcp_next[:3, 3] = T_base_tcp[:3, 3] + tw[:3] * dt
    T_cam_next = T_tcp_next @ T_tcp_camera
    moved = invert_T(T_base_camera) @ T_cam_next  # the camera's motion in its own frame
    assert np.allclose(moved[:3, 3] / dt, v_c[:3], rtol=1e-3, atol=1e-3)
    assert np.allclose(Rotation.from_matrix(moved[:3, :3]).as_rotvec() / dt, v_c[3:],
                       rtol=1e-3, atol=1e-6)


def _loop(T_start: np.ndarray, interaction: str, steps: int = 600, dt: float = 0.01,
          ids: tuple[int, ...] = tuple(range(6))) -> np.ndarray:
    gain = AdaptiveGain(4.0, 2.0, 30.0)
    desired = _features(T_DESIRED, ids)
    T = T_start
    for _ in range(steps):
        v = camera_twist(_features(T, ids), desired, gain, interaction)  # type: ignore[arg-type]
        T = _move_camera(T, v, dt)
    return T


@pytest.mark.parametrize("interaction", ["current", "desired", "mean"])
@pytest.mark.parametrize("offset", [
    ([25.0, -15.0, 10.0], [0.0, 0.0, 0.0]),  # pure translation
    ([0.0, 0.0, 0.0], [0.0, 0.0, np.radians(6.0)]),  # pure rotation about the optical axis
    ([0.0, 0.0, 0.0], [np.radians(4.0), -np.radians(3.0), 0.0]),  # pure tilt
    ([25.0, -15.0, 10.0], [0.0, 0.0, np.radians(6.0)]),  # both
])
def test_displaced_views_converge_on_the_desired_pose(
        interaction: str, offset: tuple[list[float], list[float]]) -> None:
    T_start = T_from_pose(offset[0], offset[1]) @ T_DESIRED
    T_end = _loop(T_start, interaction)
    d_mm, d_deg = pose_distance(T_end, T_DESIRED)
    assert d_mm < 1e-3 and d_deg < 1e-4


def test_four_of_six_dots_still_converge() -> None:
    T_start = T_from_pose([20.0, 10.0, -10.0], [0.0, 0.02, 0.1]) @ T_DESIRED
    d_mm, d_deg = pose_distance(_loop(T_start, "mean", ids=(0, 1, 4, 5)), T_DESIRED)
    assert d_mm < 1e-3 and d_deg < 1e-4


def test_too_few_dots_are_refused() -> None:
    f = _features(T_DESIRED, (0, 1, 2))
    with pytest.raises(ValueError, match="at least 4"):
        camera_twist(f, f, AdaptiveGain(4.0, 2.0, 30.0))


def test_adaptive_gain_runs_from_zero_to_infinity() -> None:
    g = AdaptiveGain(4.0, 1.0, 30.0)
    assert g(0.0) == pytest.approx(4.0)
    assert g(1e6) == pytest.approx(1.0)
    h = 1e-7
    assert (g(h) - g(0.0)) / h == pytest.approx(-30.0, rel=1e-3)
    up = AdaptiveGain(1.0, 4.0, -30.0)  # rising with the error is as well defined
    assert up(0.0) == pytest.approx(1.0) and up(1e6) == pytest.approx(4.0)


def test_limit_twist_keeps_direction_and_acceleration() -> None:
    t = np.array([300.0, 0.0, 0.0, 0.0, 0.0, 1.0])
    out = limit_twist(t, t * 250.0 / 300.0, 0.01, 250.0, 2.0, 1500.0, 10.0)
    assert np.allclose(out, t * 250.0 / 300.0)
    out = limit_twist(np.array([100.0, 0, 0, 0, 0, 0]), np.zeros(6), 0.01, 250.0, 2.0,
                      1500.0, 10.0)
    assert out[0] == pytest.approx(15.0)


def test_prediction_moves_features_with_the_camera_and_measured_ones_stay_at_rest() -> None:
    f = _features(T_DESIRED)
    P = (DOTS @ T_DESIRED[:3, :3].T) + T_DESIRED[:3, 3]
    same = predicted(f, np.eye(4), P)
    assert np.allclose(same.xy, f.xy)
    step = T_from_pose([1.0, 0.0, 0.0], [0.0, 0.0, 0.0])  # camera now -> then
    moved = predicted(f, step, P)
    assert np.allclose(moved.xy, project_normalised(step @ T_DESIRED, DOTS))


def test_features_from_pixels_undistort_through_the_lens() -> None:
    cam = CameraModel(800.0, 800.0, 639.5, 399.5, (-0.05, 0.01, 0.0, 0.0, 0.0))
    xy = project_normalised(T_DESIRED, DOTS)
    px = cam.distort_points(xy)
    f = features_from_view(cam, range(6), px, T_DESIRED, DOTS)
    assert np.allclose(f.xy, xy, atol=1e-6)
    assert image_error_px(f, _features(T_DESIRED), cam)[1] < 1e-3


def test_remaining_motion_is_the_tcp_displacement_the_view_asks_for() -> None:
    T_camera_tcp = T_from_pose([0.0, -60.0, 120.0], [0.0, 0.0, 0.0])
    # the camera (and the TCP with it) turned 0.05 deg about a point near the target: a
    # hair in the image, a tenth of a millimetre at the TCP
    pivot = T_from_pose(T_DESIRED[:3, :3] @ DOTS.mean(axis=0) + T_DESIRED[:3, 3], [0, 0, 0])
    turn = pivot @ T_from_pose([0, 0, 0], [np.radians(0.05), 0, 0]) @ invert_T(pivot)
    T_now = invert_T(turn) @ T_DESIRED  # the target seen from the turned camera
    cur, des = _features(T_now), _features(T_DESIRED)
    assert image_error_px(cur, des, CameraModel(800.0, 800.0, 639.5, 399.5))[0] < 0.05
    d_mm, d_deg = remaining_motion(cur, des, "mean", T_camera_tcp)
    expect_mm, expect_deg = pose_distance(turn @ T_camera_tcp, T_camera_tcp)
    assert d_mm == pytest.approx(expect_mm, rel=0.05) and expect_mm > 0.1
    assert d_deg == pytest.approx(expect_deg, rel=0.05)


def test_settle_steps_put_the_camera_back_where_the_view_was_taught() -> None:
    """From a small displacement (the settle's regime), the first-order step at the goal's
    interaction matrix, mapped through the hand-eye transform to a TCP goal, puts the camera
    back within microns; a second step from there is smaller still."""
    T_tcp_camera = T_from_pose([30.0, -60.0, 40.0], [0.1, -0.2, 0.05])
    T_base_target = T_from_pose([-480.0, -130.0, 0.0], [np.pi, 0.0, 0.0])
    T_base_camera_taught = T_base_target @ invert_T(T_DESIRED)
    desired = _features(T_DESIRED)
    T_base_tcp = T_base_camera_taught @ T_from_pose([0.3, -0.2, 0.4], [0.001, -0.002, 0.0015]) \
        @ invert_T(T_tcp_camera)
    sizes = []
    for _ in range(2):
        T_camera_target = invert_T(T_base_tcp @ T_tcp_camera) @ T_base_target
        step = settle_step(_features(T_camera_target), desired)
        sizes.append(step_size(step, invert_T(T_tcp_camera))[0])
        T_base_tcp = step_goal(T_base_tcp, T_tcp_camera, step)
    d_mm, d_deg = pose_distance(T_base_tcp @ T_tcp_camera, T_base_camera_taught)
    assert d_mm < 0.002 and d_deg < 1e-4
    assert sizes[0] > 0.3 and sizes[1] < 0.01 * sizes[0]


def test_mean_features_average_the_dots_every_view_has() -> None:
    a = _features(T_DESIRED)
    b = Features(a.ids[1:], a.xy[1:] + 1e-3, a.depth_mm[1:] + 2.0)
    m = mean_features([a, b])
    assert m.ids == a.ids[1:]
    np.testing.assert_allclose(m.xy, a.xy[1:] + 5e-4)
    np.testing.assert_allclose(m.depth_mm, a.depth_mm[1:] + 1.0)
    with pytest.raises(ValueError):
        mean_features([])


def _delayed_loop(gain: object, delay_s: float, dt: float = 0.005, steps: int = 600
                  ) -> list[float]:
    """The kinematic loop acting on views ``delay_s`` old: the pose error (mm) per step."""
    desired = _features(T_DESIRED)
    T = T_from_pose([20.0, -10.0, 8.0], [0.0, 0.0, np.radians(4.0)]) @ T_DESIRED
    seen = [T] * (round(delay_s / dt) + 1)
    errors = []
    for _ in range(steps):
        v = camera_twist(_features(seen[0]), desired, gain)  # type: ignore[arg-type]
        T = _move_camera(T, v, dt)
        seen = [*seen[1:], T]
        errors.append(pose_distance(T, T_DESIRED)[0])
    return errors


def test_the_latency_cap_keeps_a_delayed_loop_from_ringing() -> None:
    """Behind a 100 ms delay a gain of 10/s rings: it passes within 0.01 mm and swings out
    again, for seconds. Capped at 0.4 / delay (4/s) the same loop is within 0.01 mm for good
    in under a second."""
    high = AdaptiveGain(10.0, 10.0, 0.0)
    capped = LatencyCappedGain(high, 0.1, 0.4)
    assert capped.cap_per_s == pytest.approx(4.0) and capped(1.0) == pytest.approx(4.0)
    dt = 0.005

    def within_for_good_s(errors: list[float]) -> float:
        return (max(i for i, e in enumerate(errors) if e > 0.01) + 1) * dt

    ringing, damped = _delayed_loop(high, 0.1, dt), _delayed_loop(capped, 0.1, dt)
    first_within_s = next(i for i, e in enumerate(ringing) if e < 0.01) * dt
    assert first_within_s < within_for_good_s(ringing) - 0.5  # it came back out
    assert within_for_good_s(damped) < 1.0 < 2.0 < within_for_good_s(ringing)


def test_fixed_camera_drives_the_tool_plate_back_to_the_taught_view() -> None:
    """Eye-to-hand: the fixed camera sees a plate on the tool; the law's twist with the sign
    turned, mapped through a configured T_base_camera 2 mm / 0.5 deg off the true one, brings
    the TCP back to where the view was taught (the error bends the path, not the goal); the
    view's pose, the dots' motion and the pose-based goal agree with the truth."""
    from cell.servoing.ibvs import view_pose
    from cell.servoing.ibvs_mount import IbvsMount

    T_bc_true = T_from_pose([-930.0, -135.0, 866.0], [-1.93, 1.93, -0.52])
    T_bc_config = T_bc_true @ T_from_pose([1.5, -1.0, 1.2], [0.005, -0.004, 0.006])
    T_tcp_plate = T_from_pose([-48.0, -32.0, 20.0], [0.0, 0.8, 0.1])
    T_taught = T_from_pose([-480.0, -100.0, 200.0], [3.1, 0.1, 0.0])

    def seen(T_tcp: np.ndarray) -> np.ndarray:
        return invert_T(T_bc_true) @ T_tcp @ T_tcp_plate

    desired = _features(seen(T_taught))
    assert pose_distance(view_pose(desired, DOTS), seen(T_taught))[0] < 1e-9
    mount = IbvsMount(True, None, T_bc_config, view_pose(desired, DOTS))
    T = T_from_pose([20.0, -15.0, 10.0], [0.03, -0.05, 0.06]) @ T_taught
    # the dots' motion in the camera frame between two arm poses (prediction)
    P_then = DOTS @ seen(T)[:3, :3].T + seen(T)[:3, 3]
    T_next = T_from_pose([1.0, 0.5, -0.3], [0.001, 0.0, 0.002]) @ T
    M = mount.dots_motion(T_next, T)
    P_now = DOTS @ seen(T_next)[:3, :3].T + seen(T_next)[:3, 3]
    assert np.abs(P_then @ M[:3, :3].T + M[:3, 3] - P_now).max() < 0.05  # config's camera
    # the pose-based goal a view implies: the taught TCP, but for the camera's error
    T_base_plate = T_bc_config @ seen(T)
    assert pose_distance(mount.goal(T_base_plate, T, np.eye(4)), T_taught)[0] < 5.0
    gain = AdaptiveGain(4.0, 2.0, 30.0)
    dt = 0.01
    for _ in range(800):
        tw = mount.tcp_twist(_features(seen(T)), desired, gain, "mean", T)
        step = np.eye(4)
        step[:3, :3] = Rotation.from_rotvec(tw[3:] * dt).as_matrix()
        T = T.copy()
        T[:3, :3] = step[:3, :3] @ T[:3, :3]
        T[:3, 3] = T[:3, 3] + tw[:3] * dt
    d_mm, d_deg = pose_distance(T, T_taught)
    assert d_mm < 1e-3 and d_deg < 1e-4, (d_mm, d_deg)
    # the settle's step: a small view error undone in one straight step
    T_off = T_from_pose([0.3, -0.2, 0.1], [0.0, 0.001, -0.001]) @ T_taught
    step_vec = settle_step(_features(seen(T_off)), desired)
    T_stepped = mount.step_goal(T_off, step_vec)
    assert pose_distance(T_stepped, T_taught)[0] < 0.05
