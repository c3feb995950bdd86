"""The simulated world's own truth, resolved from ``[sim]`` and its ``world`` preset.

A simulator that renders with the cell's own intrinsics and mounts the camera where
``[hand_eye]`` says cannot show a calibration error: every accuracy figure measured in it is
the estimator's alone. This module decides what the simulated lens and mount really are, apart
from what the cell believes (``[camera]``, ``[hand_eye]``), so commissioning has something to
recover and benchmarks something to miss.

``world = "ideal"``: the truth is the cell's config (the estimator's own error only).
``world = "realistic"``: the truth is a device of its own: the built-in simulated cell's lens and
mount (:func:`as_built`) off their nominal values by typical commissioning-day amounts (see
:data:`REALISTIC` and docs/simulator.md for where each value comes from), whatever the config
being run says, so a commissioned config stays commissioned. Explicit ``[sim]`` /
``[sim.camera]`` values always win over the preset.

The simulated camera reports nominal intrinsics with its frames (:func:`factory_calibration`), as
an OAK reports its factory calibration: a believed value, not the lens it renders with.

Who reads it: the hardware factory builds the simulated devices to it (``fakes.sim_cell``), and
the simulated world hands it back (``Hardware.sim.truth_values()``) to the only parts of the cell
that may see the truth: the benchmarks, which score against it, and the ``/sim`` routes.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from functools import lru_cache
from pathlib import Path
from typing import Self

import numpy as np
from numpy.typing import NDArray

from cell.config.schema import CellConfig, load_config
from estimator import CameraModel
from estimator.transforms import T_from_pose

Matrix4 = NDArray[np.float64]


@dataclass(frozen=True)
class RealisticOffsets:
    """How far the realistic world's truth sits from a cell's uncommissioned config."""

    mount_position_mm: tuple[float, float, float]
    mount_rotvec_rad: tuple[float, float, float]
    focal_scale: tuple[float, float]  # true fx/fy over configured fx/fy
    principal_offset_px: tuple[float, float]  # true cx/cy minus configured
    dist: tuple[float, float, float, float, float]  # true Brown-Conrady k1 k2 p1 p2 k3


@dataclass(frozen=True)
class SimEffects:
    """The arm's true geometry and the camera's timing and image effects, beside the lens.

    ``dh_delta_*``: what the arm's true DH table adds to the nominal one the controller
    reports with. ``camera_latency_s`` (+ a half-normal jitter): mid-exposure to the frame
    being available; ``timestamp_offset_s`` (+ a normal jitter): the frame's timestamp minus
    its true mid-exposure time. ``motion_blur``: the image smeared along the motion during the
    exposure. ``gain_jitter``: a frame's random relative gain; ``flicker_depth``: the light's
    modulation at ``flicker_hz``, averaged over each exposure.
    """

    dh_delta_theta_rad: tuple[float, ...] = (0.0,) * 6
    dh_delta_d_mm: tuple[float, ...] = (0.0,) * 6
    dh_delta_a_mm: tuple[float, ...] = (0.0,) * 6
    camera_latency_s: float = 0.0
    camera_latency_jitter_s: float = 0.0
    timestamp_offset_s: float = 0.0
    timestamp_jitter_s: float = 0.0
    motion_blur: bool = False
    gain_jitter: float = 0.03
    flicker_depth: float = 0.0
    flicker_hz: float = 100.0

    @property
    def kinematics_exact(self) -> bool:
        return not any((*self.dh_delta_theta_rad, *self.dh_delta_d_mm, *self.dh_delta_a_mm))


# The ideal world: nominal kinematics, a frame available the instant it is exposed and stamped
# with its true time, no motion blur, the simulated camera's long-standing 3 % gain jitter.
IDEAL_EFFECTS = SimEffects()
# Typical values with their sources in docs/simulator.md: an uncalibrated arm's geometry off
# the nominal table by tenths of a mm and ~0.1 mrad per joint (the reported TCP ~1 mm off);
# an OAK on USB3: ~33 ms latency (std ~0.8 ms), host-synced timestamps (< 0.2 ms 1 sigma)
# that mark the end of the exposure; LED light flickering at twice a 50 Hz mains.
REALISTIC_EFFECTS = SimEffects(
    dh_delta_theta_rad=(0.0, 3e-4, -2.5e-4, 2.5e-4, -3e-4, 0.0),
    dh_delta_d_mm=(0.25, 0.0, 0.0, -0.2, 0.15, 0.0),
    dh_delta_a_mm=(0.0, 0.3, -0.3, 0.0, 0.0, 0.0),
    camera_latency_s=0.033, camera_latency_jitter_s=0.001,
    timestamp_offset_s=0.002, timestamp_jitter_s=0.0002,
    motion_blur=True, gain_jitter=0.05, flicker_depth=0.1, flicker_hz=100.0,
)


# A hand-measured bracket (calipers, a square): 1-3 mm and a few tenths of a degree off;
# nominal intrinsics from a datasheet field of view: ~0.5-1 % in focal length, a few px in the
# principal point; a small-format M12 lens of the OAK class: mild barrel distortion.
REALISTIC = RealisticOffsets(
    mount_position_mm=(1.2, -0.8, 1.5),
    mount_rotvec_rad=(0.004, -0.003, 0.006),
    focal_scale=(1.008, 1.007),
    principal_offset_px=(3.5, -2.5),
    dist=(-0.045, 0.012, 0.0004, -0.0003, 0.0),
)


@dataclass(frozen=True)
class SimTruthValues:
    """What the simulated camera really is: its lens and where it sits on the flange."""

    world: str
    camera: CameraModel
    T_flange_camera: Matrix4
    effects: SimEffects = IDEAL_EFFECTS

    def with_optics(self, camera: CameraModel, T_mount: Matrix4) -> Self:
        """The same world with the camera's lens and mount (a fixed camera's in the base
        frame) replaced: its truth after a fault at run time."""
        return dataclasses.replace(self, camera=camera, T_flange_camera=np.array(T_mount))


BUILT_IN = {"hand": "sim.toml", "fixed": "sim-fixed.toml"}


@lru_cache(maxsize=2)
def as_built(mount: str) -> CellConfig:
    """The simulated device as built: the built-in simulated cell for that camera mount.

    The realistic world's lens and mount are offsets from this, never from the config being
    run: commissioning writes its results into the config, and a truth that followed the
    config would move away by exactly what commissioning corrected."""
    return load_config(Path(__file__).parents[1] / "configs" / BUILT_IN[mount])


def _mount(config: CellConfig) -> Matrix4:
    """What ``config`` says the camera's mount is: T_base_camera (fixed) or T_flange_camera."""
    he = config.hand_eye
    if config.fixed_camera:
        assert he.T_base_camera is not None  # the schema requires it with a fixed mount
        return he.T_base_camera.T()
    return he.T_flange_camera.T()


def _nominal_lens(config: CellConfig) -> CameraModel:
    """The built-in cell's nominal lens at ``config``'s output size (a sensor mode scales the
    intrinsics)."""
    nominal = as_built("fixed" if config.fixed_camera else "hand").camera.model()
    return nominal.scaled(config.camera.width, config.camera.height)


def factory_calibration(config: CellConfig) -> CameraModel:
    """The intrinsics the simulated camera reports with its frames, as an OAK reports its
    factory calibration: in the realistic world the lens's nominal values (not the true lens,
    and not whatever the config was later given), in the ideal world the configured ones."""
    if config.sim.world == "realistic":
        return _nominal_lens(config)
    return config.camera.model()


def resolve(config: CellConfig) -> SimTruthValues:
    """The simulated camera's true intrinsics and mount for ``config`` (for a fixed camera the
    mount is ``T_base_camera``)."""
    sim, believed = config.sim, config.camera.model()
    fixed = config.fixed_camera
    if sim.world == "realistic":
        o, nominal = REALISTIC, _nominal_lens(config)
        fx, fy = nominal.fx * o.focal_scale[0], nominal.fy * o.focal_scale[1]
        cx, cy = nominal.cx + o.principal_offset_px[0], nominal.cy + o.principal_offset_px[1]
        dist: tuple[float, ...] = o.dist
        T_nominal = _mount(as_built("fixed" if fixed else "hand"))
        T_mount = T_nominal @ T_from_pose(np.array(o.mount_position_mm),
                                          np.array(o.mount_rotvec_rad))
    else:
        fx, fy, cx, cy = believed.fx, believed.fy, believed.cx, believed.cy
        dist = tuple(believed.dist)
        T_mount = _mount(config)
    sc = sim.camera
    camera = CameraModel(
        sc.fx if sc.fx is not None else fx, sc.fy if sc.fy is not None else fy,
        sc.cx if sc.cx is not None else cx, sc.cy if sc.cy is not None else cy,
        tuple(sc.dist) if sc.dist is not None else dist, believed.width, believed.height)
    pinned = sim.T_base_camera if fixed else sim.T_flange_camera
    if pinned is not None:
        T_mount = pinned.T()
    return SimTruthValues(sim.world, camera, np.asarray(T_mount, dtype=float), effects(config))


def effects(config: CellConfig) -> SimEffects:
    """The world preset's kinematic, timing and image effects; explicit ``[sim]`` values win."""
    sim = config.sim
    p = REALISTIC_EFFECTS if sim.world == "realistic" else IDEAL_EFFECTS

    def pick(value: float | None, preset: float) -> float:
        return preset if value is None else float(value)

    def six(value: list[float] | None, preset: tuple[float, ...]) -> tuple[float, ...]:
        return preset if value is None else tuple(float(x) for x in value)

    return SimEffects(
        six(sim.dh_delta_theta_rad, p.dh_delta_theta_rad), six(sim.dh_delta_d_mm,
                                                               p.dh_delta_d_mm),
        six(sim.dh_delta_a_mm, p.dh_delta_a_mm),
        pick(sim.camera_latency_s, p.camera_latency_s),
        pick(sim.camera_latency_jitter_s, p.camera_latency_jitter_s),
        pick(sim.timestamp_offset_s, p.timestamp_offset_s),
        pick(sim.timestamp_jitter_s, p.timestamp_jitter_s),
        p.motion_blur if sim.motion_blur is None else sim.motion_blur,
        pick(sim.gain_jitter, p.gain_jitter), pick(sim.flicker_depth, p.flicker_depth),
        sim.flicker_hz)
