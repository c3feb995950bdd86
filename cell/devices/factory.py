"""THE one place that builds real or simulated hardware from the config.

Everything else in the cell works on the interfaces in ``drivers`` and never asks which
implementation it has. Each device table's kind (:mod:`cell.config.devices`) has its builder
here, registered on its config class (``_build_arm``, ``_build_camera``, ``_build_gripper``),
and, where a kind has rules of its own, the problems that refuse it (``device_problems``):

- ``[robot] kind="ur"``: the UR adapter (ur_rtde) at ``robot.host``; with ``[sim]
  ur_controller`` the simulated UR controller is started on that (loopback) address first, in
  its own process, so the real adapter and the real client drive the simulated arm over the
  wire. ``kind="sim"``: the simulated arm in-process (fast tests).
- ``[camera] kind="sim"``: the simulated camera, which renders what the simulated arm's camera
  sees; ``"oak"``: a Luxonis OAK.
- ``[gripper] kind="sim"``: the simulated gripper on a TCP relay or a pseudo-terminal
  (``link``), driven through the real Modbus RTU adapter; ``"robotiq"``: the adapter on
  ``gripper.port``; ``"none"``.

The simulated parts come from one call, :func:`fakes.sim_cell.build_sim_cell`, given what to
simulate (:func:`simulated_cell_spec`) and the simulated world's truth
(:mod:`cell.devices.sim_truth`).
"""

from __future__ import annotations

import contextlib
from collections.abc import Callable
from functools import singledispatch
from typing import TYPE_CHECKING, Any, Protocol, TypeVar

import numpy as np

from cell.config.checks import Problem
from cell.config.devices import (
    CameraConfig,
    CameraConfigBase,
    DeviceConfig,
    GripperConfig,
    NoGripperConfig,
    OakCameraConfig,
    RobotConfigBase,
    RobotiqGripperConfig,
    RobotiqLink,
    SimCameraConfig,
    SimGripperConfig,
    SimRobotConfig,
    UrRobotConfig,
)
from cell.config.schema import CellConfig, ConfigError
from cell.devices import sim_truth
from cell.devices.hardware import Hardware
from drivers.arm import Arm
from drivers.camera import Camera, CameraSettings
from drivers.gripper import Gripper
from drivers.robotiq import RobotiqGripper
from fakes.sim_camera import SimCamera
from fakes.sim_cell import (
    ArmSpec,
    CameraSpec,
    FixedMount,
    GripperSpec,
    PartsSpec,
    SensorEffects,
    SimCellSpec,
    SimulatedCell,
    build_sim_cell,
)

if TYPE_CHECKING:
    from drivers.oak.camera import OakSettings  # imported when used: depthai loads slowly

Sim = SimulatedCell[Any]

SIM_CAMERA_NEEDS_SIM_ARM = ("camera.kind = \"sim\" needs a simulated robot (robot.kind = "
                            "\"sim\" or sim.ur_controller = true)")
ROBOTIQ_NEEDS_PORT = ("gripper.port: a serial device (or a socket://HOST:PORT relay) is needed "
                      "for kind = \"robotiq\"")


# -- what to simulate ---------------------------------------------------------------------------
def simulated_cell_spec(config: CellConfig) -> SimCellSpec:
    """What of ``config``'s cell the fakes simulate: the arm when its kind is not real
    hardware (the in-process arm, or the UR controller ``[sim]`` starts), the simulated camera,
    the simulated gripper, and with a simulated arm the world's parts (the target at ``[sim]
    T_base_target``)."""
    arm = None if config.robot.is_hardware(config.sim) else _arm_spec(config)
    camera = _camera_spec(config) if isinstance(config.camera, SimCameraConfig) else None
    return SimCellSpec(arm, camera, _gripper_spec(config.gripper),
                       _parts_spec(config) if arm is not None else None)


def _parts_spec(config: CellConfig) -> PartsSpec:
    return PartsSpec(config.target.model(), config.sim.T_base_target.T(),
                     config.sim.part_width_mm)


def _arm_spec(config: CellConfig, in_process: bool = False) -> ArmSpec:
    rc, sim, fx = config.robot, config.sim, sim_truth.effects(config)
    host = rc.host if isinstance(rc, UrRobotConfig) and not in_process else None
    return ArmSpec(home_joints_rad=tuple(float(q) for q in np.radians(rc.home_joints_deg)),
                   dh_delta_theta_rad=fx.dh_delta_theta_rad, dh_delta_d_mm=fx.dh_delta_d_mm,
                   dh_delta_a_mm=fx.dh_delta_a_mm, controller_host=host,
                   controller_running_at_start=sim.controller_running_at_start)


def _camera_spec(config: CellConfig) -> CameraSpec:
    sim, true = config.sim, sim_truth.resolve(config)
    fx = true.effects  # a fixed camera is the same sensor: the same timing, blur and light
    fixed = None
    if config.fixed_camera:
        fixed = FixedMount(config.tool.T_flange_tcp.T(), sim.tool_radius_mm,
                           None if sim.T_flange_board is None else sim.T_flange_board.T())
    return CameraSpec(
        lens=true.camera, reported_lens=sim_truth.factory_calibration(config),
        T_mount=true.T_flange_camera, fps=config.camera.fps, noise_std=sim.noise_std,
        blur_sigma_px=sim.blur_sigma_px, fixed=fixed,
        effects=SensorEffects(
            gain_jitter=fx.gain_jitter, latency_s=fx.camera_latency_s,
            latency_jitter_s=fx.camera_latency_jitter_s,
            timestamp_offset_s=fx.timestamp_offset_s, timestamp_jitter_s=fx.timestamp_jitter_s,
            motion_blur=fx.motion_blur, flicker_depth=fx.flicker_depth,
            flicker_hz=fx.flicker_hz))


def _gripper_spec(gripper: GripperConfig) -> GripperSpec | None:
    if not isinstance(gripper, SimGripperConfig):
        return None
    return GripperSpec(gripper.slave_id, transport=gripper.link)


# -- one builder per kind -----------------------------------------------------------------------
@singledispatch
def _build_arm(robot: RobotConfigBase, sim: Sim) -> Arm:
    raise NotImplementedError(f"no builder for [robot] kind = {type(robot).tag()!r}")


@_build_arm.register
def _ur_arm(robot: UrRobotConfig, sim: Sim) -> Arm:
    from drivers.ur.adapter import URArm

    return URArm(robot.host, connect_timeout_s=robot.connect_timeout_s,
                 call_timeout_s=robot.call_timeout_s, watchdog_s=robot.watchdog_s,
                 stale_after_s=robot.stale_after_s)


@_build_arm.register
def _sim_arm(robot: SimRobotConfig, sim: Sim) -> Arm:
    if sim.arm is None:
        raise RuntimeError("the simulated cell was built without its in-process arm")
    return sim.arm


@singledispatch
def _build_camera(camera: CameraConfigBase, sim: Sim) -> Camera:
    raise NotImplementedError(f"no builder for [camera] kind = {type(camera).tag()!r}")


@_build_camera.register
def _sim_camera(camera: SimCameraConfig, sim: Sim) -> Camera:
    if sim.camera is None:
        raise ConfigError(SIM_CAMERA_NEEDS_SIM_ARM)
    settings = _sensor_settings(camera)
    if settings is not None:
        try:
            sim.camera.apply_settings(settings)
        except ValueError as err:
            raise ConfigError(f"camera: {err}") from err
    return sim.camera


@_build_camera.register
def _oak_camera(camera: OakCameraConfig, sim: Sim) -> Camera:
    from drivers.oak.camera import OakCamera

    return OakCamera(oak_settings(camera))


@singledispatch
def _build_gripper(gripper: DeviceConfig, sim: Sim) -> Gripper | None:
    raise NotImplementedError(f"no builder for [gripper] kind = {type(gripper).tag()!r}")


@_build_gripper.register
def _robotiq(gripper: RobotiqGripperConfig, sim: Sim) -> Gripper | None:
    if not gripper.port:
        raise ConfigError(ROBOTIQ_NEEDS_PORT)
    return robotiq_gripper(gripper, gripper.port)


@_build_gripper.register
def _sim_gripper(gripper: SimGripperConfig, sim: Sim) -> Gripper | None:
    if sim.gripper is None:
        raise RuntimeError("the simulated cell was built without its gripper")
    return robotiq_gripper(gripper, sim.gripper.port)


@_build_gripper.register
def _no_gripper(gripper: NoGripperConfig, sim: Sim) -> Gripper | None:
    return None


# Each device table's builders, by the table's name: every kind of the table has its own.
BUILDERS = {"robot": _build_arm, "camera": _build_camera, "gripper": _build_gripper}


def _sensor_settings(camera: CameraConfigBase) -> CameraSettings | None:
    """The sensor settings ``[camera]`` states (None: the device's defaults)."""
    if camera.exposure_us is None and camera.iso is None and camera.focus is None:
        return None
    return CameraSettings(camera.exposure_us, camera.iso, camera.focus)


def oak_settings(camera: OakCameraConfig) -> OakSettings:
    """The OAK adapter's settings from ``[camera]``; unset sensor values keep its defaults."""
    from drivers.oak.camera import OakSettings

    sensor: dict[str, Any] = {}
    if camera.exposure_us is not None:
        sensor["exposure_us"] = camera.exposure_us
    if camera.iso is not None:
        sensor["iso"] = camera.iso
    try:
        return OakSettings(width=camera.width, height=camera.height, fps=camera.fps,
                           socket=camera.socket, device_id=camera.device_id or None,
                           focus=camera.focus, **sensor)
    except ValueError as err:
        raise ConfigError(f"camera: {err}") from err


def robotiq_gripper(link: RobotiqLink, port: str) -> RobotiqGripper:
    """The Modbus RTU adapter on ``port`` with the link and timing settings of ``link``."""
    return RobotiqGripper(port, slave_id=link.slave_id, baudrate=link.baudrate,
                          timeout_s=link.timeout_s, retries=link.retries,
                          motion_timeout_s=link.motion_timeout_s,
                          activation_timeout_s=link.activation_timeout_s)


# -- what refuses a kind ------------------------------------------------------------------------
@singledispatch
def device_problems(device: DeviceConfig, config: CellConfig) -> list[Problem]:
    """Why the factory would refuse to build ``device`` in ``config``'s cell (a kind without
    rules of its own: nothing)."""
    return []


@device_problems.register
def _sim_camera_problems(camera: SimCameraConfig, config: CellConfig) -> list[Problem]:
    problems = []
    if config.robot.is_hardware(config.sim):
        problems.append(Problem("camera.kind", SIM_CAMERA_NEEDS_SIM_ARM))
    settings = _sensor_settings(camera)
    if settings is not None:
        try:
            SimCamera.check_settings(settings, camera.fps)
        except ValueError as err:
            problems.append(Problem("camera", str(err)))
    return problems


@device_problems.register
def _oak_problems(camera: OakCameraConfig, config: CellConfig) -> list[Problem]:
    try:
        oak_settings(camera)
    except ConfigError as err:
        return [Problem("camera", str(err))]
    return []


@device_problems.register
def _robotiq_problems(gripper: RobotiqGripperConfig, config: CellConfig) -> list[Problem]:
    return [] if gripper.port else [Problem("gripper.port", ROBOTIQ_NEEDS_PORT)]


def hardware_problems(config: CellConfig) -> list[Problem]:
    """Every reason :func:`build_hardware` refuses this config, found without building or
    touching anything, so ``cell config check`` fails on what ``cell serve`` refuses."""
    return [p for device in config.devices() for p in device_problems(device, config)]


def all_simulated(config: CellConfig) -> bool:
    """True when the config builds only fakes (then the sample API tokens are allowed)."""
    return not config.has_real_device()


# -- building -----------------------------------------------------------------------------------
def build_hardware(config: CellConfig, wait_ready: bool = True) -> Hardware:
    """Create (not connect) the devices the config names; Cell.start connects them.
    ``wait_ready=False``: return while a simulated controller still boots in its own process
    (``Hardware.wait_ready`` waits for it; the service's first connect calls it)."""
    problems = hardware_problems(config)
    if problems:
        raise ConfigError("cannot build the hardware:\n  "
                          + "\n  ".join(str(p) for p in problems), problems)
    sim = build_sim_cell(simulated_cell_spec(config), sim_truth.resolve(config))
    closers: list[Callable[[], None]] = [sim.close]
    try:
        arm = _build_arm(config.robot, sim)
        closers.append(arm.disconnect)
        camera = _build_camera(config.camera, sim)
        closers.append(camera.disconnect)
        gripper = _build_gripper(config.gripper, sim)
        if gripper is not None:
            closers.append(gripper.disconnect)
        if wait_ready:
            sim.wait_ready()
    except BaseException:
        _release(closers)
        raise
    simulated = all_simulated(config)
    return Hardware(arm=arm, camera=camera, gripper=gripper, simulated=simulated,
                    sim=sim.world if simulated else None, closers=closers,
                    wait_ready=sim.wait_ready)


def build_camera(config: CellConfig) -> tuple[Camera, Callable[[], None]]:
    """Only the camera, for commissioning commands, and a function that releases it.

    A simulated camera needs a simulated arm to hang on: it gets an in-process one at the
    configured home pose, so it shows what the simulated cell sees at home.
    """
    spec = SimCellSpec()
    if isinstance(config.camera, SimCameraConfig):
        spec = SimCellSpec(arm=_arm_spec(config, in_process=True), camera=_camera_spec(config),
                           parts=_parts_spec(config))
    return _one_device(_build_camera, config.camera, spec)


def build_gripper(gripper: GripperConfig) -> tuple[Gripper | None, Callable[[], None]]:
    """Only the gripper (None for ``kind = "none"``), for commissioning commands, and a
    function that releases it; a simulated one, without a world around it, closes on
    nothing."""
    spec = SimCellSpec(gripper=_gripper_spec(gripper))
    return _one_device(_build_gripper, gripper, spec)


class _Device(Protocol):
    def disconnect(self) -> None: ...


D = TypeVar("D", bound=_Device | None)


def _one_device(build: Callable[[Any, Sim], D], device: CameraConfig | GripperConfig,
                spec: SimCellSpec) -> tuple[D, Callable[[], None]]:
    sim: Sim = build_sim_cell(spec, None)
    try:
        built = build(device, sim)
    except BaseException:
        sim.close()
        raise

    def release() -> None:
        if built is not None:
            built.disconnect()
        sim.close()

    return built, release


def _release(closers: list[Callable[[], None]]) -> None:
    for close in reversed(closers):
        with contextlib.suppress(Exception):  # cleaning up after a failed build
            close()
