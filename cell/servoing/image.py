"""The image-based law (IBVS, mode ``"ibvs"``): drive the taught view's dots to where they were
taught, approaching and tracking.

Its measurements are views: the matched dots' normalised image points (undistorted through the
lens model), their depths and 3-D positions from the frame's pose estimate. Only the dots the
taught view also has are used (the estimator's correspondence names them), so a dot that
leaves the image or is hidden just drops out; fewer than 4 and the frame is no view. Each tick
takes the newest view's features (with ``[ibvs] predict_motion``, moved on by the arm's motion
since their exposure: :func:`cell.servoing.ibvs.predicted`), computes the law's camera twist
(:mod:`cell.servoing.ibvs`) with the adaptive gain capped at ``gain_latency_product`` over the
loop's delay (the view's age when used, averaged), maps it to the TCP through the camera's
mount (:mod:`cell.servoing.ibvs_mount`) and caps it by the ``[servo]`` limits. A view's
pose-based goal is checked against the envelope and reported as the estimated pose error; the
law never uses it.

Converged (approach): over the last ``converge_frames`` views, the image error averaged under
``tolerance_px_rms`` / ``tolerance_px_max``, averaged because the view's weakest direction (a
turn about a point near the target, seen only through perspective) is below one frame's noise;
the TCP motion the window's mean view still asks for (:func:`cell.servoing.ibvs.
remaining_motion`) under ``tolerance_mm`` / ``tolerance_deg``, since the pixels alone cannot
see that direction; and the arm nearly still, since a window's mean is small too while the arm
swings through the view. Then, with ``settle_frames``, the final settle
(:func:`settle_on_views`), which can also count the loop's last views taken within
``settle_carry_mm`` / ``_deg`` of where the arm came to rest, carried there by the arm's own
motion (off by default: such a view brings its own pixel-grid bias, docs/ibvs.md).
"""

from __future__ import annotations

import logging
import time
from collections import deque
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from cell.core import CellCore
from cell.error_codes import ErrorCode
from cell.errors import RefusedError
from cell.motion.limits import linear_path
from cell.results import Pose
from cell.servoing.clock import TwistClock
from cell.servoing.ibvs import (
    MIN_FEATURES,
    AdaptiveGain,
    Features,
    LatencyCappedGain,
    features_from_view,
    image_error_px,
    limit_twist,
    predicted,
    remaining_motion,
)
from cell.servoing.ibvs_mount import IbvsMount
from cell.servoing.ibvs_settle import mean_features, settle_step, step_size
from cell.servoing.law import Law, Loop, LoopMode, Reading, StreamCaps, Tick, Unusable
from cell.servoing.record import FrameStats
from cell.servoing.view_bound import Resolution, frame_noise_px, resolution
from cell.vision.locate import Located
from drivers.arm import ArmState
from estimator import CameraModel
from estimator.transforms import pose_distance

log = logging.getLogger(__name__)
Matrix4 = NDArray[np.float64]
Vec = NDArray[np.float64]
LATENCY_SMOOTHING_S = 0.2  # the time constant the loop's delay is averaged over
STILL_SHARE = 0.5  # converged only if the arm moves less than this share of the tolerances
# within the loop's delay
RECENT_VIEWS = 60  # the loop's last views kept for the settle (2 s at 30 fps)


class TooFewDots(Unusable):
    """A view with fewer than ``MIN_FEATURES`` of the taught dots."""


@dataclass(frozen=True)
class View:
    """One measured frame, reduced to what the law needs."""

    features: Features  # only the dots the taught view has
    points_camera_mm: NDArray[np.float64]  # those dots in the camera frame (pose estimate)
    T_base_tcp: Matrix4  # at mid-exposure
    T_base_target: Matrix4  # the pose estimate in the base frame (for the goal check)
    exposure_s: float
    sequence: int
    border_px: float  # the smallest distance of a matched dot from the image's edge
    missing: tuple[int, ...]  # taught dots not matched in this frame


def view_of(located: Located, desired: Features, camera: CameraModel,
            target_points_mm: NDArray[np.float64]) -> View:
    """The view ``located`` gives of the taught dots ``desired``, through the lens model the
    estimator used (teaching used it too). :class:`Unusable` without matched dots,
    :class:`TooFewDots`; a degenerate estimate raises ValueError, IndexError or LinAlgError."""
    result = located.result
    if result.image_points_px is None or not result.matched_ids:
        raise Unusable(None)
    seen = features_from_view(camera, result.matched_ids, result.image_points_px,
                              result.T_camera_target, target_points_mm)
    common = tuple(i for i in desired.ids if i in seen.ids)
    if len(common) < MIN_FEATURES:
        raise TooFewDots(RefusedError(
            ErrorCode.target_lost, f"only {len(common)} of the taught view's dots matched (at "
            f"least {MIN_FEATURES} are needed)"), failed=False)
    px = np.asarray(result.image_points_px, dtype=float).reshape(-1, 2)
    border = float(np.min(np.concatenate([px[:, 0], px[:, 1], camera.width - 1 - px[:, 0],
                                          camera.height - 1 - px[:, 1]])))
    P = np.asarray(target_points_mm, dtype=float)[list(common)]
    Tc = result.T_camera_target
    return View(seen.subset(common), P @ Tc[:3, :3].T + Tc[:3, 3], located.T_base_tcp,
                located.T_base_target, located.frame_timestamp_s, located.frame_sequence,
                border, tuple(i for i in desired.ids if i not in common))


class ImageLaw(Law[View, View]):
    """The law of one IBVS run (module doc): ``desired``, the taught view's features."""

    name = "IBVS"
    doing = "while servoing on the image"
    unseen = "view were not usable"
    event_mode = "ibvs"
    # a frame without the target is judged by the stall clock only
    blind_frames_examined = False

    def __init__(self, core: CellCore, desired: Features, T_target_tcp: Matrix4,
                 mode: LoopMode) -> None:
        self.core, self.desired, self.T_target_tcp, self.mode = core, desired, T_target_tcp, mode
        self.sc, self.ic = core.config.servo, core.config.ibvs
        self.phase = f"ibvs_{mode}"
        self.timeout_s = self.ic.approach_timeout_s
        self.caps = StreamCaps.of(core.config)
        self.camera: CameraModel = core.locator.camera_model
        self.mount = IbvsMount.of(core.frames, desired, core.locator.target.points_mm)
        self.gain = AdaptiveGain(self.ic.gain_at_zero_per_s, self.ic.gain_at_infinity_per_s,
                                 self.ic.slope_at_zero)
        self.few_dots = 0  # frames with fewer than MIN_FEATURES taught dots
        self.missing_dots = 0  # views without some of the taught dots
        self.min_dots = len(desired.ids)
        self.min_border_px = float("inf")
        self.window: deque[NDArray[np.float64]] = deque(maxlen=self.ic.converge_frames)
        self.last_px = (float("nan"), float("nan"))
        self.last_pose = (float("nan"), float("nan"))
        self.last_step = (float("nan"), float("nan"))
        self.resolution: Resolution | None = None  # what the converged window resolves
        self.phases: dict[str, float] = {}  # when each phase began (s from the loop's start)
        self.delay_s: float | None = None  # the loop's delay, averaged: the view's age + a tick
        self.t_tick: float | None = None
        self.gain_caps: list[float] = []
        self.settle_steps: list[list[float]] | None = None
        self.settle_frames: list[list[int]] | None = None  # per step: still, carried
        self.recent: deque[View] = deque(maxlen=RECENT_VIEWS)

    # -- per frame -----------------------------------------------------------------------------
    def seed(self, first: Located) -> View | None:
        """The approach's own locate, whose frame serves as the loop's first view (the next
        frame would otherwise be waited for and estimated again)."""
        if time.monotonic() - first.frame_timestamp_s > self.core.config.limits.max_pose_age_s:
            return None
        return self.read(first)

    def read(self, located: Located) -> View:
        # the lens model the estimator used for this frame (teaching used it too)
        locator = self.core.locator
        try:
            return view_of(located, self.desired, locator.camera_model, locator.target.points_mm)
        except TooFewDots:
            self.few_dots += 1
            raise
        except (ValueError, IndexError, np.linalg.LinAlgError) as err:
            # a degenerate estimate (a dot behind the camera, a bad id): not a view
            log.warning("frame %d gave no IBVS view: %r", located.frame_sequence, err)
            raise Unusable(RefusedError(ErrorCode.estimation_failed,
                                        f"no view: {err}")) from err

    def admit(self, view: View) -> None:
        self.min_dots = min(self.min_dots, len(view.features.ids))
        self.min_border_px = min(self.min_border_px, view.border_px)
        if view.missing:
            self.missing_dots += 1

    # -- per tick ------------------------------------------------------------------------------
    def aim(self, now: Tick[View]) -> View | None:
        return None if now.silence.lost else now.newest

    def judge(self, view: View, T_tcp: Matrix4, new: bool, t_s: float, prev: Vec
              ) -> Reading | None:
        if not new:
            return None
        self.recent.append(view)
        desired = self.desired.subset(view.features.ids)
        self.phases.setdefault("first_view", t_s)
        goal = self.mount.goal(view.T_base_target, view.T_base_tcp, self.T_target_tcp)
        self.core.arm.guard.check_path(linear_path(T_tcp, goal), "ibvs goal estimate")
        self.last_pose = pose_distance(view.T_base_tcp, goal)
        self.last_px = image_error_px(view.features, desired, self.camera)
        errors = {"image_error_px": self.last_px[0], "error_mm": self.last_pose[0],
                  "error_deg": self.last_pose[1]}
        converged = self.mode == "approach" and self._converged(view, desired, t_s, prev)
        return Reading(errors, converged, {"dots": len(view.features.ids)})

    def _converged(self, view: View, desired: Features, t_s: float, prev: Vec) -> bool:
        ic, window = self.ic, self.window
        window.append(view.features.xy - desired.xy)
        step = remaining_motion(view.features, desired, ic.interaction,
                                self.mount.camera_tcp(view.T_base_tcp))
        if step[0] < ic.tolerance_mm and step[1] < ic.tolerance_deg:
            self.phases.setdefault("first_frame_within", t_s)
        if len({e.shape for e in window}) > 1:  # the dots changed: start again
            window.clear()
            window.append(view.features.xy - desired.xy)
        if len(window) < ic.converge_frames:
            return False
        self.last_px = _window_px(window, self.camera)
        # the motion the window's mean view asks for: a mean of per-frame steps would be each
        # frame's noise, not the view's offset
        mean_view = Features(desired.ids, desired.xy + np.mean(window, axis=0),
                             view.features.depth_mm)
        self.last_step = remaining_motion(mean_view, desired, ic.interaction,
                                          self.mount.camera_tcp(view.T_base_tcp))
        # and the arm nearly still: a window's mean is also small while the arm swings through
        # the view; within the loop's delay (what the newest view is behind the arm) it may
        # move half the tolerance
        self.resolution = resolution(
            mean_view, desired, ic.interaction, self.mount.camera_tcp(view.T_base_tcp),
            self.camera.fx, max(frame_noise_px(list(window), self.camera.fx),
                                ic.centroid_bias_px), ic.centroid_bias_px, len(window))
        lag_s = 0.0 if self.delay_s is None else self.delay_s
        image = self.last_px[0] < ic.tolerance_px_rms and self.last_px[1] < ic.tolerance_px_max
        pose = self.last_step[0] < ic.tolerance_mm and self.last_step[1] < ic.tolerance_deg
        still = float(np.linalg.norm(prev[:3])) * lag_s < STILL_SHARE * ic.tolerance_mm \
            and float(np.degrees(np.linalg.norm(prev[3:]))) * lag_s \
            < STILL_SHARE * ic.tolerance_deg
        for phase, within in (("window_image_within", image), ("window_view_within", pose),
                              ("window_still", still)):
            if within:
                self.phases.setdefault(phase, t_s)
        return image and pose and still

    def twist(self, view: View, T_tcp: Matrix4, state: ArmState, t: float, clock: TwistClock
              ) -> Vec:
        ic = self.ic
        now_features = predicted(view.features,
                                 self.mount.dots_motion(T_tcp, view.T_base_tcp),
                                 view.points_camera_mm) if ic.predict_motion else view.features
        # what the command acts on is as old as the view, or with the view moved on by the
        # arm's motion since its exposure, as old as the arm's state
        age_s = max(t - (state.timestamp_s if ic.predict_motion else view.exposure_s),
                    0.0) + self.sc.tick_s
        self.delay_s = age_s if self.delay_s is None or self.t_tick is None else \
            self.delay_s + (age_s - self.delay_s) * min(1.0, (t - self.t_tick)
                                                        / LATENCY_SMOOTHING_S)
        self.t_tick = t
        gain = LatencyCappedGain(self.gain, self.delay_s, ic.gain_latency_product)
        self.gain_caps.append(gain.cap_per_s)
        twist = self.mount.tcp_twist(now_features, self.desired.subset(view.features.ids),
                                     gain, ic.interaction, T_tcp)
        c = self.caps
        return limit_twist(twist, clock.prev, clock.step(), c.max_speed_mm_s, c.max_rate_rad_s,
                           c.accel_mm_s2, c.accel_rad_s2)

    def left(self) -> str:
        return f"image error {self.last_px[0]:.3f} px RMS, {self.last_px[1]:.3f} px max"

    def lost_detail(self, stats: FrameStats) -> str:
        return f"{self.few_dots} with fewer than {MIN_FEATURES} taught dots"

    # -- at the end ----------------------------------------------------------------------------
    def settle(self, loop: Loop[View], converged_s: float | None) -> float | None:
        if converged_s is not None:
            self.phases["converged"] = converged_s
        self.phases["stopped"] = time.monotonic() - loop.t0
        if self.mode != "approach" or self.ic.settle_frames <= 0:
            return converged_s
        settled = settle_on_views(loop, self.desired, self.mount, self.caps, list(self.recent))
        self.settle_steps, self.settle_frames = settled.steps_mm_deg, settled.frames
        self.phases["settled"] = time.monotonic() - loop.t0
        return self.phases["settled"]

    def result(self, loop: Loop[View], reached: Matrix4) -> dict[str, Any]:
        view = loop.newest()
        out: dict[str, Any] = {
            "frames_with_too_few_dots": self.few_dots,
            "frames_missing_dots": self.missing_dots,
            "min_dots_used": self.min_dots,
            "dots_taught": len(self.desired.ids),
            "min_dot_border_px": None if not np.isfinite(self.min_border_px)
            else self.min_border_px,
            "interaction": self.ic.interaction,
            "image_error_px_rms": self.last_px[0], "image_error_px_max": self.last_px[1],
        }
        res = self.resolution
        if res is not None and np.isfinite(self.last_step[0]):
            # the view's claim: the motion it still asks for and what it cannot resolve
            out.update(estimated_error_mm=self.last_step[0] + res.mm,
                       estimated_error_deg=self.last_step[1] + res.deg,
                       resolution_mm=res.mm, resolution_deg=res.deg)
        else:  # no window judged: the newest frame's pose-based figure
            out.update(estimated_error_mm=self.last_pose[0],
                       estimated_error_deg=self.last_pose[1])
        if view is not None:
            out["T_base_target"] = Pose.from_T(view.T_base_target)
            out["goal_T_base_tcp"] = Pose.from_T(view.T_base_target @ self.T_target_tcp)
        out.update(view_error_mm=self.last_step[0], view_error_deg=self.last_step[1],
                   phases_s={k: round(v, 4) for k, v in self.phases.items()},
                   gain_cap_per_s=_percentiles(self.gain_caps))
        if self.settle_steps is not None:
            out["settle_steps_mm_deg"] = self.settle_steps
            out["settle_frames_still_carried"] = self.settle_frames
        return out


def _window_px(window: deque[NDArray[np.float64]], camera: CameraModel) -> tuple[float, float]:
    """RMS and max over the dots of the image error averaged over the window's frames (px):
    where the view rests, its frame-to-frame noise averaged out."""
    d = np.mean(np.stack(list(window)), axis=0) * np.array([camera.fx, camera.fy])
    n = np.linalg.norm(d, axis=1)
    return float(np.sqrt(np.mean(n ** 2))), float(np.max(n))


def _percentiles(xs: list[float]) -> dict[str, float] | None:
    if not xs:
        return None
    p5, p50, p95 = np.percentile(xs, [5, 50, 95])
    return {"p5": round(float(p5), 2), "median": round(float(p50), 2), "p95": round(float(p95), 2)}


@dataclass(frozen=True)
class SettleOutcome:
    """What the settle did: each step's size ``[mm, deg]`` and the frames it averaged
    ``[still, carried]``."""

    steps_mm_deg: list[list[float]]
    frames: list[list[int]]


def settle_on_views(loop: Loop[View], desired: Features, mount: IbvsMount, caps: StreamCaps,
                    earlier: list[View]) -> SettleOutcome:
    """Average ``settle_frames`` views of the still arm with the ``earlier`` ones taken near
    where it rests (:func:`carried_views`), and make the step that mean asks for; again from
    the new rest, up to ``settle_steps`` times."""
    ic, arm = loop.core.config.ibvs, loop.core.arm
    out = SettleOutcome([], [])
    for _ in range(ic.settle_steps):
        views = _rest_views(loop, ic.settle_frames, time.monotonic())
        T_rest = views[-1].T_base_tcp
        still = {v.sequence for v in views}
        carried = carried_views([v for v in earlier if v.sequence not in still], T_rest,
                                mount, ic.settle_carry_mm, ic.settle_carry_deg)
        step = settle_step(mean_features([v.features for v in views] + carried), desired)
        size = step_size(step, mount.camera_tcp(T_rest))
        out.steps_mm_deg.append([round(size[0], 4), round(size[1], 5)])
        out.frames.append([len(views), len(carried)])
        if size[0] < ic.settle_tolerance_mm and size[1] < ic.settle_tolerance_deg:
            break
        loop.motion.raise_if_cancelled("before the IBVS settle step")
        goal = mount.step_goal(T_rest, step)
        try:
            arm.move_linear(goal, caps.max_speed_mm_s, caps.accel_mm_s2, what="IBVS settle step")
        finally:
            loop.stop()
        earlier = earlier + views
    return out


def carried_views(views: list[View], T_base_tcp_rest: Matrix4, mount: IbvsMount,
                  within_mm: float, within_deg: float) -> list[Features]:
    """The features of the ``views`` whose arm pose at exposure was within ``within_mm`` /
    ``within_deg`` of the rest pose, moved on to that pose by the arm's motion since (through
    the hand-eye transform).

    Why: the loop's last frames see the arm creeping the last tenths of a millimetre to where
    it stops; they are as good as still frames once carried there, and free. The carry errs
    by the hand-eye's error times the motion carried (0.5 deg over 0.2 mm: 0.002 mm) and by
    the arm's speed times the frame's timestamp error, both small against one frame's noise
    (~0.12 mm at the TCP from 456 mm), which the extra frames average down."""
    out: list[Features] = []
    if within_mm <= 0 or within_deg <= 0:  # carrying switched off
        return out
    for v in views:
        d_mm, d_deg = pose_distance(T_base_tcp_rest, v.T_base_tcp)
        if d_mm <= within_mm and d_deg <= within_deg:
            out.append(predicted(v.features, mount.dots_motion(T_base_tcp_rest, v.T_base_tcp),
                                 v.points_camera_mm))
    return out


def _rest_views(loop: Loop[View], n: int, after_s: float) -> list[View]:
    """``n`` new views exposed after ``after_s`` (the arm is still by then)."""
    views: list[View] = []
    deadline = time.monotonic() + 2.0 + 6.0 * n / loop.core.config.camera.fps
    while len(views) < n:
        loop.motion.raise_if_cancelled("while settling on the image")
        view = loop.newest()
        if view is not None and view.exposure_s > after_s and \
                (not views or view.sequence != views[-1].sequence):
            views.append(view)
        elif time.monotonic() > deadline:
            raise RefusedError(ErrorCode.target_lost, f"only {len(views)} of {n} views of "
                               "the still arm arrived for the IBVS settle")
        else:
            time.sleep(0.002)
    return views
