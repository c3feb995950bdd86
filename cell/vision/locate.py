"""Locate: the freshest frame, its target pose, paired with the arm pose at capture time.

``T_base_target = T_base_tcp(t) @ inv(T_flange_tcp) @ T_flange_camera @ T_camera_target`` with
``t`` the frame's mid-exposure time looked up in the arm's pose history, so a frame taken while
the arm moves is mapped with the pose the arm had when the frame was taken.
"""

from __future__ import annotations

import logging
import threading
import time
from collections import Counter
from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from cell.error_codes import ErrorCode
from cell.errors import CellError, RefusedError, UnavailableError
from cell.results.consistency import Consistency
from cell.results.locate import LocateQuality, LocateResult, PickOrder
from cell.results.pose import Pose
from cell.vision.consistency import consistency
from cell.vision.frames import CellFrames, mean_pose
from cell.vision.imagelog import ImageLog
from cell.vision.instance_ids import InstanceIds
from cell.vision.intrinsics import IntrinsicsPolicy, IntrinsicsSource
from cell.vision.parts import LocatedParts, located_parts
from cell.vision.search_window import SearchWindows
from drivers.arm import Arm
from drivers.camera import Camera, Frame
from drivers.errors import ConnectionLostError, DriverError
from estimator import CameraModel, EstimationError, PoseResult, Target
from estimator.instances import InstanceFinder
from estimator.pipeline import Estimator
from estimator.transforms import invert_T, pose_distance

log = logging.getLogger(__name__)
Matrix4 = NDArray[np.float64]
IN_USE = "target"  # the name of the layout in use, when a locate of all parts names none
# A followed part is the one whose dots' centre lies this close to where it was seen last.
FOLLOW_MM = 20.0


def _history_error(err: DriverError) -> UnavailableError:
    """The arm's pose history unreadable: its lost link is ``arm_disconnected``."""
    code = (ErrorCode.arm_disconnected if isinstance(err, ConnectionLostError)
            else ErrorCode(err.code))
    return UnavailableError(code, f"reading the arm pose history: {err}")


@dataclass(frozen=True)
class Located:
    """A target pose in the base frame and the evidence it came from."""

    T_base_target: Matrix4
    T_camera_target: Matrix4
    T_base_tcp: Matrix4  # at the (last) frame's capture time
    result: PoseResult  # of the last frame
    frame_timestamp_s: float
    frame_sequence: int
    n_frames: int
    spread_mm: float  # largest distance of a single-frame estimate from the mean
    located_at_s: float  # time.monotonic()
    spread_deg: float = 0.0  # largest rotation of a single-frame estimate from the mean
    rms_px_frames: tuple[float, ...] = ()  # reprojection rms of each frame averaged

    @property
    def frame_rms_px(self) -> tuple[float, ...]:
        """The reprojection rms of each frame it comes from."""
        return self.rms_px_frames or (float(self.result.rms_px),)

    def answer(self, now_s: float) -> LocateResult:
        """The locate answer every interface publishes; ``now_s`` (time.monotonic()) dates
        the frame's age."""
        r = self.result
        return LocateResult(
            T_base_target=Pose.from_T(self.T_base_target),
            T_camera_target=Pose.from_T(self.T_camera_target),
            T_base_tcp=Pose.from_T(self.T_base_tcp),
            quality=LocateQuality(
                rms_px=float(r.rms_px),
                max_residual_px=float(np.max(r.residuals_px)) if len(r.residuals_px) else 0.0,
                ambiguous=bool(r.ambiguous), converged=bool(r.converged),
                n_points=len(r.matched_ids),
                covariance=None if r.covariance is None else r.covariance.tolist(),
                frame_age_s=max(0.0, now_s - self.frame_timestamp_s), n_frames=self.n_frames,
                spread_mm=self.spread_mm, spread_deg=self.spread_deg),
            frame_sequence=self.frame_sequence,
            # one locate, one arm pose: residuals and frame spread, no motion to judge
            consistency=Consistency.model_validate(
                consistency([("locate", self)], np.zeros(3), target_at_rest=False)))


class Locator:
    """Owns the estimators; thread-safe. Failed frames go to the optional image log."""

    def __init__(self, camera_model: CameraModel, target: Target, camera: Camera, arm: Arm,
                 frames: CellFrames, fps: float, image_log: ImageLog | None = None,
                 intrinsics_source: IntrinsicsSource = "config",
                 order: PickOrder = "nearest_to_camera_axis", same_part_mm: float = 5.0
                 ) -> None:
        self.camera = camera
        self.arm = arm
        self.frames = frames
        self.fps = fps
        self.image_log = image_log
        self.target = target
        self.camera_model = camera_model
        self.intrinsics = IntrinsicsPolicy(camera_model, intrinsics_source)
        self._estimator = Estimator(camera_model, target)
        self._windows = SearchWindows(frames.is_fixed)  # where the next frame's dots can be
        self._estimator_lock = threading.Lock()
        # a separate one keeps the live view from disturbing locate's tracking state
        self._preview = Estimator(camera_model, target)
        self._preview_lock = threading.Lock()
        self._lock = threading.Lock()
        self.outcomes: Counter[str] = Counter()  # ok / failed / error, for /metrics
        self.seconds_sum = 0.0
        # per search mode ("tracking", "window", "full", "failed"): frames and seconds
        self.search_frames: Counter[str] = Counter()
        self.search_seconds: dict[str, float] = {}
        self.last: Located | None = None
        self.last_frame: Frame | None = None
        self.order: PickOrder = order
        self.part_ids = InstanceIds(same_part_mm)
        self.last_parts: LocatedParts | None = None
        self._followed_mm: NDArray[np.float64] | None = None  # see follow()
        self._beside: dict[str, Target] = {}  # see follow()

    def set_frames(self, frames: CellFrames) -> None:
        """New calibrated mounts; the last locate was mapped with the old ones, so drop it."""
        self.frames = frames
        self.last = None
        self.last_parts = None
        self.part_ids.forget()
        with self._estimator_lock:
            self._windows = SearchWindows(frames.is_fixed)

    def use_target(self, target: Target) -> bool:
        """Look for another dot layout from now on (a recipe's target); the last locate was
        of the old one, so it is dropped. False when it is the layout already in use."""
        same = (target.polarity == self.target.polarity
                and target.dot_diameter_mm == self.target.dot_diameter_mm
                and np.array_equal(target.points_mm, self.target.points_mm))
        if same:
            return False
        with self._estimator_lock, self._preview_lock:
            self.target = target
            self._estimator = Estimator(self.camera_model, target)
            self._preview = Estimator(self.camera_model, target)
            self._windows.forget()
        self.last = None
        return True

    def follow(self, centre_base_mm: NDArray[np.float64] | None,
               beside: Mapping[str, Target] | None = None) -> None:
        """Locate one part among several (a pick's): from now on every estimate searches the
        frame for every part of the layout and takes the one whose dots' centre lies within
        ``FOLLOW_MM`` of where it was seen last, starting at ``centre_base_mm`` (None: back to
        the single-target search). Identical parts side by side would otherwise be one
        ambiguous target to the single search, which may lock onto the neighbour. ``beside``:
        the other layouts that may share the view (a recipe's other targets), searched for
        too, so their dots are explained as their parts and not taken for a part of this
        layout's with dots missing."""
        with self._lock:
            self._followed_mm = (None if centre_base_mm is None
                                 else np.asarray(centre_base_mm, dtype=float).reshape(3).copy())
            self._beside = {} if centre_base_mm is None or beside is None else {
                name: t for name, t in beside.items() if name != IN_USE}
        with self._estimator_lock:
            self._windows.forget()

    def latest_frame(self, timeout_s: float = 1.0) -> Frame:
        try:
            frame = self.camera.latest_frame(timeout_s=timeout_s)
        except DriverError as err:
            raise UnavailableError(ErrorCode.camera_lost, f"no camera frame: {err}") from err
        self.last_frame = frame
        return frame

    def preview(self, estimate: bool) -> tuple[Frame, PoseResult | None, str | None]:
        """The freshest frame and, if asked, what the estimator sees in it (live view)."""
        frame = self.latest_frame()
        if not estimate:
            return frame, None, None
        try:
            with self._preview_lock:
                return frame, self._preview.estimate(frame.image), None
        except EstimationError as err:
            return frame, None, err.message

    def locate(self, n_frames: int = 1, after_s: float | None = None) -> Located:
        """Estimate from ``n_frames`` successive frames captured no earlier than ``after_s``
        (None: the call), each paired with the arm pose at its capture time, and average the
        base-frame results (noise drops as 1/sqrt(n)). A frame from before the call may show a
        part that has since been put down or taken away: a PLC that places a part and asks at
        once must get the part where it is now, not the mean of its old and new place."""
        if after_s is None:
            after_s = time.monotonic()
        if not self.camera.is_connected:
            raise UnavailableError(ErrorCode.camera_lost, "the camera is not connected")
        self._require_arm()
        estimates: list[Matrix4] = []
        rms_px: list[float] = []
        last: tuple[Frame, PoseResult, Matrix4] | None = None
        for _ in range(max(1, n_frames)):
            seq = -1 if last is None else last[0].sequence
            frame = self._fresh_frame(after_s)
            while frame.sequence == seq:
                frame = self._fresh_frame(frame.timestamp_s + 1e-6)
            try:
                T_base_tcp = self.arm.pose_at(frame.timestamp_s)
            except LookupError:
                # a frame older than the history (a link that just came back): the next one
                frame = self._fresh_frame(time.monotonic())
                T_base_tcp = self._pose_at(frame)
            except DriverError as err:
                raise _history_error(err) from err
            result = self._estimate(frame, T_base_tcp)
            estimates.append(self.frames.T_base_target(T_base_tcp, result.T_camera_target))
            rms_px.append(float(result.rms_px))
            last = (frame, result, T_base_tcp)
        assert last is not None
        frame, result, T_base_tcp = last
        T_mean = mean_pose(estimates) if len(estimates) > 1 else estimates[0]
        spread = max(float(np.linalg.norm(T[:3, 3] - T_mean[:3, 3])) for T in estimates)
        spread_deg = max(pose_distance(T, T_mean)[1] for T in estimates)
        T_camera_target = invert_T(self.frames.T_base_camera(T_base_tcp)) @ T_mean
        loc = Located(T_mean, T_camera_target, T_base_tcp, result, frame.timestamp_s,
                      frame.sequence, len(estimates), spread, time.monotonic(), spread_deg,
                      tuple(rms_px))
        self.last = loc
        return loc

    def locate_all(self, layouts: Mapping[str, Target] | None = None) -> LocatedParts:
        """Every part of ``layouts`` (by name; None: the layout in use, named ``target``) in
        the freshest frame, mapped with the arm pose at its capture time, numbered and
        ordered (:mod:`cell.vision.parts`). No part in view is an answer, not an error.
        Does not touch the single-target search's tracking state."""
        if not self.camera.is_connected:
            raise UnavailableError(ErrorCode.camera_lost, "the camera is not connected")
        self._require_arm()
        frame = self._fresh_frame(None)
        T_base_tcp = self._pose_at(frame)
        wanted = dict(layouts) if layouts else {IN_USE: self.target}
        t0 = time.perf_counter()
        try:
            with self._estimator_lock:
                self._use_intrinsics(frame.camera)
                model = self.camera_model
            search = InstanceFinder(model, wanted).find(frame.image)
        except Exception as err:  # an estimator bug must not take the service down
            log.exception("the search for every part failed on frame %d", frame.sequence)
            raise self._failed(frame, "error", RefusedError(
                ErrorCode.estimator_failed, f"the estimator failed unexpectedly: {err!r}")) from err
        self._count_search("parts", t0)
        parts = located_parts(search, wanted, self.frames, T_base_tcp, self.part_ids,
                              self.order, frame.timestamp_s, frame.sequence)
        self.last_parts = parts
        return parts

    def measure(self, after_sequence: int, timeout_s: float = 0.5) -> Located:
        """One frame newer than ``after_sequence``, estimated (tracking mode after the first)
        and mapped into the base frame with the arm pose at its mid-exposure time: a locate of
        one frame for the closed loops, which need no averaging and no arm at rest (``last``
        stays the last :meth:`locate`'s). CellError when the frame does not show the target."""
        frame = self.latest_frame(timeout_s)
        if frame.sequence <= after_sequence:
            raise RefusedError(ErrorCode.no_new_frame, "no frame newer than the last one")
        T_base_tcp = self._pose_at(frame)
        result = self._estimate(frame, T_base_tcp)
        return Located(self.frames.T_base_target(T_base_tcp, result.T_camera_target),
                       result.T_camera_target, T_base_tcp, result, frame.timestamp_s,
                       frame.sequence, 1, 0.0, time.monotonic())

    def _require_arm(self) -> None:
        """A frame is mapped into the base frame with the arm's pose: with the arm's link
        down there is none to map it with (``arm_disconnected``, not a stale history)."""
        try:
            connected = self.arm.state().connected
        except DriverError as err:
            raise UnavailableError(ErrorCode.arm_disconnected,
                                   f"reading the arm state: {err}") from err
        if not connected:
            raise UnavailableError(ErrorCode.arm_disconnected, "the arm is not connected, so a "
                                   "frame cannot be mapped into the base frame; check the "
                                   "controller and network (the cell reconnects by itself)")

    def _pose_at(self, frame: Frame) -> Matrix4:
        try:
            return self.arm.pose_at(frame.timestamp_s)
        except LookupError as err:
            self._require_arm()  # a history that ends because the link did
            raise RefusedError(ErrorCode.stale_pose, "the arm's pose history does not cover the "
                               f"frame's capture time: {err}") from err
        except DriverError as err:
            raise _history_error(err) from err

    def _fresh_frame(self, after_s: float | None) -> Frame:
        """The freshest frame, captured no earlier than ``after_s`` (monotonic)."""
        deadline = time.monotonic() + 2.0 + 3.0 / self.fps
        while True:
            frame = self.latest_frame()
            if after_s is None or frame.timestamp_s >= after_s:
                return frame
            if time.monotonic() > deadline:
                raise UnavailableError(ErrorCode.camera_stalled,
                                       "the camera delivers no new frames; check its connection")
            time.sleep(0.2 / self.fps)

    def _use_intrinsics(self, device: CameraModel) -> None:
        """Frames carry the device's intrinsics; the policy (``[camera] intrinsics``) decides
        which the estimators compute with (call with the estimator lock held)."""
        model = self.intrinsics.model_for(device)
        if model != self.camera_model:
            self.camera_model = model
            self._estimator = Estimator(model, self.target)
            self._preview = Estimator(model, self.target)
            self._windows.forget()

    def _estimate(self, frame: Frame, T_base_tcp: Matrix4) -> PoseResult:
        """The frame's estimate; the search starts in the window where the last frame's dots
        can be now (:mod:`cell.vision.search_window`) when the track does not hold. A
        followed part (:meth:`follow`) is found among every part in the frame."""
        with self._lock:
            followed = self._followed_mm
        if followed is not None:
            return self._estimate_followed(frame, T_base_tcp, followed)
        t0 = time.perf_counter()
        try:
            with self._estimator_lock:
                self._use_intrinsics(frame.camera)
                h, w = frame.image.shape[:2]
                window = self._windows.window(frame.timestamp_s, T_base_tcp, w, h)
                try:
                    result = self._estimator.estimate(frame.image, window)
                except EstimationError:  # the sighting stays: the window grows with its age
                    self._count_search("failed", t0)
                    raise
                self._count_search(self._estimator.last_mode, t0)
                self._windows.seen(result, self.target.points_mm, self.camera_model,
                                   frame.timestamp_s, T_base_tcp,
                                   self.frames.T_base_camera(T_base_tcp))
        except EstimationError as err:
            raise self._failed(frame, "failed", RefusedError(
                ErrorCode(err.code), f"target not located: {err.message}")) from err
        except Exception as err:  # an estimator bug must not take the service down
            log.exception("estimator failed on frame %d", frame.sequence)
            raise self._failed(frame, "error", RefusedError(
                ErrorCode.estimator_failed, f"the estimator failed unexpectedly: {err!r}")) from err
        with self._lock:
            self.outcomes["ok"] += 1
            self.seconds_sum += time.perf_counter() - t0
        return result

    def _estimate_followed(self, frame: Frame, T_base_tcp: Matrix4,
                           followed_mm: NDArray[np.float64]) -> PoseResult:
        t0 = time.perf_counter()
        with self._lock:
            wanted = {**self._beside, IN_USE: self.target}
        try:
            with self._estimator_lock:
                self._use_intrinsics(frame.camera)
                search = InstanceFinder(self.camera_model, wanted).find(frame.image)
        except Exception as err:  # an estimator bug must not take the service down
            log.exception("the search for the followed part failed on frame %d", frame.sequence)
            raise self._failed(frame, "error", RefusedError(
                ErrorCode.estimator_failed, f"the estimator failed unexpectedly: {err!r}")) from err
        self._count_search("parts", t0)
        T_base_camera = self.frames.T_base_camera(T_base_tcp)
        centre_target = self.target.points_mm.mean(axis=0)
        best: tuple[float, PoseResult, NDArray[np.float64]] | None = None
        ours = [inst for inst in search.instances if inst.layout == IN_USE]
        for inst in ours:
            T = T_base_camera @ inst.pose.T_camera_target
            centre = T[:3, :3] @ centre_target + T[:3, 3]
            d = float(np.linalg.norm(centre - followed_mm))
            if best is None or d < best[0]:
                best = (d, inst.pose, centre)
        if best is None or best[0] > FOLLOW_MM:
            where = ", ".join(f"{v:.1f}" for v in followed_mm)
            nearest = "" if best is None else f"; the nearest is {best[0]:.1f} mm away"
            raise self._failed(frame, "failed", RefusedError(
                ErrorCode.target_not_visible,
                f"the part being followed (dots' centre at [{where}] mm) is not in this frame: "
                f"{len(ours)} part(s) of its layout seen{nearest}"))
        with self._lock:
            if self._followed_mm is not None:
                self._followed_mm = best[2]
            self.outcomes["ok"] += 1
            self.seconds_sum += time.perf_counter() - t0
        return best[1]

    def _count_search(self, mode: str, t0: float) -> None:
        with self._lock:
            self.search_frames[mode] += 1
            self.search_seconds[mode] = (self.search_seconds.get(mode, 0.0)
                                         + time.perf_counter() - t0)

    def _failed(self, frame: Frame, outcome: str, err: CellError) -> CellError:
        with self._lock:
            self.outcomes[outcome] += 1
        if self.image_log is not None:
            self.image_log.save(frame.image, {"code": err.code, "message": err.message,
                                              "sequence": frame.sequence,
                                              "timestamp_s": frame.timestamp_s})
        return err
