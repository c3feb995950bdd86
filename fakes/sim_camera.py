"""A simulated eye-in-hand camera behind :class:`drivers.camera.Camera`.

A background thread "exposes" a frame every 1/fps seconds: it samples the arm's flange pose at
mid-exposure from ``pose_source`` (the simulated controller's engine), so a moving arm changes
what the camera sees exactly as on a real cell, and every part of the world
(:class:`fakes.parts.SimParts`) where it truly is then. The image itself is rendered only when
someone asks for the frame (:func:`fakes.render.render_scene`, ~6-10 ms a part at 1280x800): the
scene at that
instant is kept, so the result is the same as rendering eagerly but the idle cell burns no CPU.
Nor does it sample the pose 30 times a second for nobody: once no frame has been taken for
``IDLE_AFTER_S`` the sensor exposes only every ``IDLE_PERIOD_S`` (enough to notice a pose
source that went away), and the next ``latest_frame`` wakes it and gets a fresh exposure
(taken after the call), at most an exposure later than a streaming camera's newest frame.

What a real camera adds on top, each off unless asked for (the ``realistic`` world turns them
on, cell.devices.sim_truth): a frame becomes available ``latency_s`` (+ jitter) after its
mid-exposure, its timestamp is off the true mid-exposure time by an offset and a jitter
(:attr:`SimCamera.exposure_log` keeps the truth per frame), the image is smeared along the
motion during the exposure, and the light flickers.

Faults as an integrator meets them: dropped frames (sequence gaps), a lost device
(``latest_frame`` raises ConnectionLostError until restored) and a blocked view (a dark,
featureless image, e.g. a hand or a cover in front of the lens).
"""

from __future__ import annotations

import dataclasses
import math
import threading
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass

import cv2
import numpy as np
from numpy.typing import NDArray

from drivers.camera import CameraSettings, Frame
from drivers.errors import ConnectionLostError, DeviceTimeoutError
from estimator import CameraModel, Target
from estimator.transforms import invert_T
from fakes.parts import SimParts
from fakes.render import motion_smear, render_scene

Matrix4 = NDArray[np.float64]
PoseSource = Callable[[], tuple[Matrix4, float]]  # () -> (T_base_flange mm, time.monotonic())

BLOCKED_LEVEL = 12.0  # grey level of a covered lens
NOMINAL_ISO = 100
MAX_ISO = 1600
# The simulated lens has a focus motor (0..255, like the OAK's); the target is sharp at this
# position and every step away adds defocus blur, as a real lens does.
SHARP_FOCUS = 120
DEFOCUS_PX_PER_STEP = 1.0 / 16.0
IDLE_AFTER_S = 2.0  # no frame taken for this long: the sensor rests
IDLE_PERIOD_S = 0.5  # a resting sensor's exposures
MAX_SMEAR_SPAN_S = 0.25  # two pose samples further apart do not give the motion blur


@dataclass(frozen=True)
class _Exposure:
    """What the sensor saw at one instant: enough to render the image later."""

    sequence: int
    timestamp_s: float
    scene: tuple[tuple[Target, Matrix4], ...]  # each part's layout and T_camera_part
    gain: float  # exposure x ISO relative to nominal, times the frame's jitter
    blocked: bool
    blur_sigma_px: float  # the lens blur plus any defocus
    lens: CameraModel  # the true lens then: the image is rendered with it, whatever came later
    T_base_flange: Matrix4 | None = None  # the arm's flange then (what a fixed camera may see)
    true_time_s: float = 0.0  # the true mid-exposure time (timestamp_s is what the cell sees)
    available_s: float = 0.0  # when the frame reaches the host
    smear_px: tuple[float, float] = (0.0, 0.0)  # image motion of part 0 over the exposure
    T_base_camera: Matrix4 | None = None  # where the camera truly was


@dataclass(frozen=True)
class ExposureTruth:
    """One frame's timing truth: what the cell is told against what happened."""

    sequence: int
    true_time_s: float  # mid-exposure, time.monotonic
    timestamp_s: float  # the frame's timestamp
    available_s: float  # when it could be handed out
    smear_px: tuple[float, float]
    gain: float  # the frame's brightness relative to nominal (settings, jitter, flicker)


class SimCamera:
    """Renders the world's parts as seen from ``T_base_flange @ T_flange_camera`` at each
    frame."""

    def __init__(
        self, camera: CameraModel, parts: SimParts, T_flange_camera: Matrix4,
        pose_source: PoseSource, *, fps: float = 15.0,
        exposure_s: float = 0.004, noise_std: float = 1.5, blur_sigma_px: float = 0.7,
        lighting_gradient: float = 0.1, exposure_jitter: float = 0.03, seed: int | None = None,
        latency_s: float = 0.0, latency_jitter_s: float = 0.0, timestamp_offset_s: float = 0.0,
        timestamp_jitter_s: float = 0.0, motion_blur: bool = False, flicker_depth: float = 0.0,
        flicker_hz: float = 100.0, reported_camera: CameraModel | None = None,
    ) -> None:
        if not 0 < fps <= 120:
            raise ValueError(f"fps must be within (0, 120], got {fps}")
        if not 0 < exposure_s < 1.0 / fps:
            raise ValueError(f"exposure_s must be positive and shorter than a frame, got "
                             f"{exposure_s}")
        self.camera = camera
        # what the device says its intrinsics are (an OAK's factory calibration): a
        # calibration, so not necessarily ``camera``, the lens the images are rendered with
        self.reported_camera = camera if reported_camera is None else reported_camera
        self.parts = parts
        self.T_flange_camera = np.array(T_flange_camera, dtype=float)
        self.pose_source = pose_source
        self.fps = fps
        self.exposure_s = exposure_s
        self.noise_std = noise_std
        self.blur_sigma_px = blur_sigma_px
        self.lighting_gradient = lighting_gradient
        self.exposure_jitter = exposure_jitter
        self.latency_s, self.latency_jitter_s = float(latency_s), float(latency_jitter_s)
        self.timestamp_offset_s = float(timestamp_offset_s)
        self.timestamp_jitter_s = float(timestamp_jitter_s)
        self.motion_blur = bool(motion_blur)
        self.flicker_depth, self.flicker_hz = float(flicker_depth), float(flicker_hz)
        self._rng = np.random.default_rng(seed)
        self._flicker_phase_rad = (float(self._rng.uniform(0.0, 2.0 * math.pi))
                                   if self.flicker_depth > 0 else 0.0)
        self._pending: deque[_Exposure] = deque()  # exposed, not yet at the host
        self.exposure_log: deque[ExposureTruth] = deque(maxlen=512)
        self._prev_sample: tuple[Matrix4, float] | None = None  # the last exposure's pose
        self._iso = NOMINAL_ISO
        self._nominal_exposure_s = exposure_s
        self._focus: int | str = "auto"
        self._cond = threading.Condition()
        self._latest: _Exposure | None = None
        self._handed_out = -1
        self._rendered: tuple[int, NDArray[np.uint8]] | None = None
        self._sequence = 0
        self._drop_next = 0
        self._drop_probability = 0.0
        self._lost = False
        self._blocked = False
        self._error: str | None = None
        self.frames_dropped = 0
        self._thread: threading.Thread | None = None
        self._stop = threading.Event()
        self._wake = threading.Event()  # a reader wants a frame from a resting sensor
        self._last_taken_s = time.monotonic()

    # -- faults ------------------------------------------------------------------------------
    def drop_frames(self, count: int = 1, probability: float | None = None) -> None:
        """Skip the next ``count`` exposures; with ``probability``, drop that share from now on."""
        with self._cond:
            self._drop_next += count
            if probability is not None:
                self._drop_probability = float(probability)

    def set_lost(self, lost: bool) -> None:
        """Unplug (True) or re-plug (False) the simulated device."""
        with self._cond:
            self._lost = lost
            self._cond.notify_all()

    def set_blocked(self, blocked: bool) -> None:
        with self._cond:
            self._blocked = blocked

    # -- the true optics ---------------------------------------------------------------------
    def optics(self) -> tuple[CameraModel, Matrix4]:
        """The lens the images are rendered with and where the camera truly sits: on the
        flange (``T_flange_camera``), for a fixed camera in the base frame."""
        with self._cond:
            return self.camera, self._mount_locked().copy()

    def set_optics(self, lens: CameraModel, T_mount: Matrix4) -> None:
        """Knock the camera or refocus its lens: render with ``lens`` from ``T_mount`` (as
        :meth:`optics`) from the next exposure on. An exposure already taken keeps the optics
        it was taken with, so every frame is wholly the old truth or the new one. The frame's
        reported intrinsics stay the device's calibration. ValueError, nothing changed, for a
        lens of another image size or a mount that is not a rigid transform."""
        T = np.array(T_mount, dtype=float)
        if (T.shape != (4, 4) or not np.all(np.isfinite(T))
                or not np.allclose(T[:3, :3] @ T[:3, :3].T, np.eye(3), atol=1e-6)
                or not np.allclose(T[3], (0.0, 0.0, 0.0, 1.0))):
            raise ValueError("the camera's mount must be a finite rigid 4x4 transform")
        with self._cond:
            if (lens.width, lens.height) != (self.camera.width, self.camera.height):
                raise ValueError(f"the lens must keep the sensor's {self.camera.width}x"
                                 f"{self.camera.height} image, got {lens.width}x{lens.height}")
            self.camera = lens
            self._set_mount_locked(T)

    def _mount_locked(self) -> Matrix4:
        return self.T_flange_camera

    def _set_mount_locked(self, T_mount: Matrix4) -> None:
        self.T_flange_camera = T_mount

    # -- Camera interface --------------------------------------------------------------------
    def get_settings(self) -> CameraSettings:
        """The simulated sensor has manual exposure and gain and a motorised focus.

        Exposure and ISO scale the image's brightness (the construction-time exposure at ISO
        100 is nominal; too much saturates the dots into the plate, too little sinks them in
        noise); a manual focus away from the sharp position blurs the image."""
        with self._cond:
            focus = self._focus
            return CameraSettings(exposure_us=round(self.exposure_s * 1e6), iso=self._iso,
                                  focus="auto" if focus == "auto" else int(focus))

    @staticmethod
    def check_settings(settings: CameraSettings, fps: float) -> None:
        """ValueError naming the first setting this camera cannot take at ``fps``."""
        if settings.exposure_us is not None and not 0 < settings.exposure_us * 1e-6 < 1.0 / fps:
            raise ValueError(f"exposure_us must be within (0, {1e6 / fps:.0f}) at "
                             f"{fps:g} fps, got {settings.exposure_us}")
        if settings.iso is not None and not NOMINAL_ISO <= settings.iso <= MAX_ISO:
            raise ValueError(f"iso must be within [{NOMINAL_ISO}, {MAX_ISO}], got {settings.iso}")
        focus = settings.focus
        if focus is not None and focus != "auto" and (
                isinstance(focus, bool) or not isinstance(focus, int) or not 0 <= focus <= 255):
            raise ValueError(f"focus must be a lens position within [0, 255] or 'auto', got "
                             f"{focus!r}")

    def apply_settings(self, settings: CameraSettings) -> CameraSettings:
        self.check_settings(settings, self.fps)
        exposure_s = self.exposure_s
        if settings.exposure_us is not None:
            exposure_s = settings.exposure_us * 1e-6
        focus = settings.focus
        with self._cond:
            self.exposure_s = exposure_s
            if settings.iso is not None:
                self._iso = settings.iso
            if focus is not None:
                self._focus = focus
        return self.get_settings()

    def _brightness(self) -> float:
        """Exposure x ISO relative to nominal (call with the lock held)."""
        return (self.exposure_s / self._nominal_exposure_s) * (self._iso / NOMINAL_ISO)

    def _blur_px(self) -> float:
        """The lens blur plus the defocus of a manual focus (call with the lock held)."""
        if self._focus == "auto":
            return self.blur_sigma_px
        defocus = abs(int(self._focus) - SHARP_FOCUS) * DEFOCUS_PX_PER_STEP
        return float(np.hypot(self.blur_sigma_px, defocus))

    @property
    def is_connected(self) -> bool:
        with self._cond:
            return self._thread is not None and not self._lost and self._error is None

    def connect(self) -> None:
        with self._cond:
            if self._lost:
                raise ConnectionLostError("simulated camera is unplugged")
            if self._thread is not None:
                return
            self._stop.clear()
            self._wake.clear()
            self._error = None
            self._last_taken_s = time.monotonic()
            self._thread = threading.Thread(target=self._run, name="sim-camera", daemon=True)
            self._thread.start()

    def disconnect(self) -> None:
        self._stop.set()
        self._wake.set()
        thread, self._thread = self._thread, None
        if thread is not None:
            thread.join(timeout=2.0)
        with self._cond:
            self._latest = None
            self._cond.notify_all()

    def latest_frame(self, timeout_s: float = 1.0) -> Frame:
        now = time.monotonic()
        deadline = now + timeout_s
        with self._cond:
            min_sequence = 0
            if now - self._last_taken_s > IDLE_AFTER_S:  # resting: its newest frame is old
                min_sequence = self._sequence + 1
                self._wake.set()
            self._last_taken_s = now
            while True:
                if self._thread is None:
                    raise ConnectionLostError("simulated camera is not connected")
                if self._lost:
                    raise ConnectionLostError("simulated camera lost (device unplugged)")
                if self._error is not None:
                    raise ConnectionLostError(f"simulated camera stopped: {self._error}")
                next_due = self._promote_locked(time.monotonic())
                exp = self._latest
                if (exp is not None and exp.sequence != self._handed_out
                        and exp.sequence >= min_sequence):
                    self._handed_out = exp.sequence
                    break
                remaining = deadline - time.monotonic()
                if remaining <= 0:
                    raise DeviceTimeoutError(
                        f"no frame from the simulated camera within {timeout_s} s")
                if next_due is not None:
                    remaining = min(remaining, max(0.0005, next_due - time.monotonic()))
                self._cond.wait(remaining)
        return Frame(self._render(exp), exp.timestamp_s, exp.sequence, self.reported_camera)

    # -- internals ---------------------------------------------------------------------------
    def _promote_locked(self, now_s: float) -> float | None:
        """Hand the newest exposure that has reached the host to ``_latest``; the time the
        next one arrives (None: nothing on the way). Call with the lock held."""
        while self._pending and self._pending[0].available_s <= now_s:
            self._latest = self._pending.popleft()
        return self._pending[0].available_s if self._pending else None

    def _render(self, exp: _Exposure) -> NDArray[np.uint8]:
        cached = self._rendered
        if cached is not None and cached[0] == exp.sequence:
            return cached[1]
        with self._cond:  # the generator is shared with the exposure thread
            rng = np.random.default_rng(self._rng.integers(0, 2**63 - 1))
        h, w = exp.lens.height, exp.lens.width
        if exp.blocked:
            # the sensor's noise about a dark level, drawn as render_target draws it (cv2.randn,
            # float32): a real camera costs the host nothing for a dark frame, and a float64
            # normal draw over the frame cost the cell's process ~50 ms per covered frame
            img = np.empty((h, w), np.float32)
            cv2.randn(img, np.full(1, BLOCKED_LEVEL), np.full(1, float(self.noise_std)))
            image = np.asarray(cv2.convertScaleAbs(img), dtype=np.uint8)
        else:  # a part whose origin is behind the camera is not drawn
            front = [(t, T) for t, T in exp.scene if T[2, 3] > 0]
            image = render_scene(
                exp.lens, front, blur_sigma_px=exp.blur_sigma_px, noise_std=self.noise_std,
                lighting_gradient=self.lighting_gradient if front else 0.0, rng=rng,
            )
        if self.motion_blur and not exp.blocked:
            image = motion_smear(image, exp.smear_px)
        if exp.gain != 1.0:  # one saturating multiply-add pass, cheap at any size
            image = np.asarray(cv2.convertScaleAbs(image, alpha=exp.gain), dtype=np.uint8)
        self._rendered = (exp.sequence, image)
        return image

    def _expose(self) -> None:
        """Take one exposure: sample the pose at mid-exposure and keep the scene. The motion
        blur's image motion comes from this sample and the previous exposure's (no extra pose
        reads: each is a round trip to the simulated controller that would delay the frame)."""
        T_base_flange, t_s = self.pose_source()
        T_base_flange = np.asarray(T_base_flange, dtype=float)
        prev, self._prev_sample = self._prev_sample, (T_base_flange, float(t_s))
        with self._cond:
            self._sequence += 1
            drop = self._drop_next > 0 or (
                self._drop_probability > 0 and self._rng.random() < self._drop_probability)
            if drop:
                self._drop_next = max(0, self._drop_next - 1)
                self.frames_dropped += 1
                return
            gain = self._brightness() * (1.0 + float(self._rng.normal(0.0, self.exposure_jitter)))
            gain *= self._flicker_locked(float(t_s))
            T_base_camera, seen = self._view(T_base_flange, float(t_s))
            T_camera_base = invert_T(T_base_camera)
            scene = tuple((t, T_camera_base @ T) for t, T in seen)
            smear = (0.0, 0.0)
            if self.motion_blur and prev is not None and 0.0 < t_s - prev[1] <= MAX_SMEAR_SPAN_S:
                smear = self._smear_locked(prev, (T_base_flange, float(t_s)))
            t_true = float(t_s)
            stamp = t_true + self.timestamp_offset_s
            if self.timestamp_jitter_s > 0:
                stamp += float(self._rng.normal(0.0, self.timestamp_jitter_s))
            exp = _Exposure(
                self._sequence, stamp, scene, gain, self._blocked, self._blur_px(),
                self.camera, T_base_flange, t_true, t_true, smear, T_base_camera)
            if self.latency_s > 0 or self.latency_jitter_s > 0:
                jitter = abs(float(self._rng.normal(0.0, self.latency_jitter_s))) \
                    if self.latency_jitter_s > 0 else 0.0
                due = t_true + max(self.latency_s + jitter, self.exposure_s / 2.0)
                exp = dataclasses.replace(exp, available_s=due)
                self._pending.append(exp)
            else:
                self._latest = exp
            self.exposure_log.append(ExposureTruth(exp.sequence, t_true, stamp,
                                                   exp.available_s, smear, gain))
            self._cond.notify_all()

    def _flicker_locked(self, t_mid_s: float) -> float:
        """The light's mean level over the exposure around ``t_mid_s`` (1: steady light)."""
        if self.flicker_depth <= 0:
            return 1.0
        w = 2.0 * math.pi * self.flicker_hz
        a, b = t_mid_s - self.exposure_s / 2.0, t_mid_s + self.exposure_s / 2.0
        phase = self._flicker_phase_rad
        mean_sin = (math.cos(w * a + phase) - math.cos(w * b + phase)) / (w * (b - a))
        return 1.0 + self.flicker_depth * mean_sin

    def _smear_locked(self, start: tuple[Matrix4, float], end: tuple[Matrix4, float]
                      ) -> tuple[float, float]:
        """The image motion (px) of part 0's centre over one exposure: its motion between two
        pose samples (the previous exposure's and this one's) scaled to the exposure time, as
        a constant velocity over that span."""
        px = []
        for T_flange, t in (start, end):
            T_base_camera, seen = self._view(T_flange, t)
            if not seen:
                return (0.0, 0.0)
            target, T_base_seen = seen[0]
            centre = np.r_[target.points_mm.mean(axis=0), 1.0]
            p = (invert_T(T_base_camera) @ T_base_seen @ centre)[:3]
            if p[2] <= 1e-6:
                return (0.0, 0.0)
            px.append(np.array([self.camera.fx * p[0] / p[2], self.camera.fy * p[1] / p[2]]))
        span_s = end[1] - start[1]
        if span_s <= 1e-6:
            return (0.0, 0.0)
        d = (px[1] - px[0]) * (self.exposure_s / span_s)
        return (float(d[0]), float(d[1]))

    def _view(self, T_base_flange: Matrix4, t_s: float
              ) -> tuple[Matrix4, list[tuple[Target, Matrix4]]]:
        """``(T_base_camera, [(layout, T_base_part), ...])`` of one exposure (call with the
        lock held): the camera rides on the flange and sees every part; a fixed camera
        (:mod:`fakes.fixed_camera`) overrides."""
        return T_base_flange @ self.T_flange_camera, self.parts.scene_at(t_s, T_base_flange)

    def _resting(self) -> bool:
        with self._cond:
            return time.monotonic() - self._last_taken_s > IDLE_AFTER_S

    def _run(self) -> None:
        period = 1.0 / self.fps
        next_start = time.monotonic()
        while not self._stop.is_set():
            if self._resting():
                self._wake.wait(IDLE_PERIOD_S)
                self._wake.clear()
                if self._stop.is_set():
                    break
                next_start = time.monotonic()
            mid = next_start + self.exposure_s / 2.0
            if self._stop.wait(max(0.0, mid - time.monotonic())):
                break
            with self._cond:
                lost = self._lost
            if not lost:
                try:
                    self._expose()
                except Exception as err:  # the pose source (arm simulation) is away
                    with self._cond:
                        self._error = f"pose source failed: {err}"
                        self._cond.notify_all()
                else:
                    if self._error is not None:  # it came back: frames flow again
                        with self._cond:
                            self._error = None
            next_start += period
            if next_start < time.monotonic() - period:  # fell behind (loaded host): skip ahead
                next_start = time.monotonic()

