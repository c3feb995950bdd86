"""THE one place that builds real or simulated hardware from the config.

Everything else in the cell works on the interfaces in ``drivers`` and never asks which
implementation it has. Choices:
- ``[robot] kind="sim"``: the simulated arm in-process (fast tests);
  ``kind="ur"``: the real UR adapter (ur_rtde) at ``robot.host``; with ``[sim] ur_controller``
  the simulated UR controller is started on that (loopback) address first, in its own process
  (see fakes.ur_controller.process), so the real adapter
  and the real client drive the simulated arm over the wire.
- ``[camera] kind="sim"``: the simulated eye-in-hand camera, which renders what the simulated
  arm's camera sees; ``"oak"``: a Luxonis OAK.
- ``[gripper] kind="sim"``: the fake gripper on a pseudo-terminal, driven through the real
  Modbus RTU adapter; ``"robotiq"``: the adapter on ``gripper.port``; ``"none"``.
"""

from __future__ import annotations

import contextlib
import os
import signal
import time
from collections.abc import Callable
from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import NDArray

from cell.config.checks import Problem
from cell.config.schema import CellConfig, ConfigError
from cell.devices import sim_truth
from cell.devices.hardware import Hardware
from drivers.arm import Arm
from drivers.camera import Camera, CameraSettings
from drivers.gripper import Gripper
from drivers.robotiq import RobotiqGripper
from estimator.transforms import T_from_ur_pose, invert_T
from fakes.fixed_camera import FixedSimCamera
from fakes.gripper import FakeGripper, LineFault
from fakes.sim_arm import SimArm
from fakes.sim_camera import SimCamera
from fakes.ur_controller.process import ControllerProcess
from fakes.ur_sim.engine import MotionEngine
from fakes.ur_sim.kinematics import UR5E, UR5eKinematics

if TYPE_CHECKING:
    from drivers.oak.camera import OakSettings  # imported when used: depthai loads slowly

Matrix4 = NDArray[np.float64]
PoseSource = Callable[[], tuple[Matrix4, float]]


def true_kinematics(config: CellConfig) -> UR5eKinematics | None:
    """The arm's true geometry when it differs from the nominal table the controller reports
    with (``[sim]`` DH errors; None: the nominal table is the truth)."""
    fx = sim_truth.effects(config)
    if fx.kinematics_exact:
        return None
    return UR5eKinematics(UR5E.perturbed(fx.dh_delta_theta_rad, fx.dh_delta_d_mm,
                                         fx.dh_delta_a_mm))


def _true_flange_and_tcp(kin: UR5eKinematics | None, q: Any, tcp_pose: Any, tcp_offset: Any
                         ) -> tuple[Matrix4, Matrix4]:
    """``(T_base_flange, T_base_tcp)`` where the arm really is: the controller's report
    (nominal kinematics) or, with a true geometry, its forward kinematics at the joints."""
    T_flange_tcp = T_from_ur_pose(tcp_offset)
    if kin is None:
        T_tcp = T_from_ur_pose(tcp_pose)
        return T_tcp @ invert_T(T_flange_tcp), T_tcp
    T_flange = kin.forward(q)
    return T_flange, T_flange @ T_flange_tcp


class _EngineTruth:
    """The simulated arm's true state, read from an in-process engine."""

    def __init__(self, engine: MotionEngine, kin: UR5eKinematics | None = None) -> None:
        self.engine = engine
        self.kin = kin

    def flange_and_tcp(self) -> tuple[Matrix4, Matrix4, float]:
        snap = self.engine.snapshot()
        T_flange, T_tcp = _true_flange_and_tcp(self.kin, snap.q, snap.tcp_pose, snap.tcp_offset)
        return T_flange, T_tcp, snap.host_monotonic_s

    def protective_stop(self, reason: str) -> None:
        self.engine.trigger_protective_stop(reason)


class _ProcessTruth:
    """The same, from a simulated controller in its own process (over its control channel).

    ur_rtde's constructors hold the GIL while talking to the controller, so a controller in
    the client's process would deadlock; time.monotonic is system-wide, so its timestamps
    compare with ours. The controller can be killed and started again (a controller reboot):
    meanwhile the arm stands where it was, so the last pose read stays the truth.
    """

    def __init__(self, host: str, start: bool, kin: UR5eKinematics | None = None) -> None:
        self.host = host
        self.kin = kin
        self.ctl: ControllerProcess | None = ControllerProcess(host) if start else None
        self._last: tuple[Matrix4, Matrix4] | None = None

    def flange_and_tcp(self) -> tuple[Matrix4, Matrix4, float]:
        ctl = self.ctl
        try:
            if ctl is None or not ctl.alive:
                raise RuntimeError("the simulated controller is not running")
            st = ctl.state()
        except Exception as err:  # down: the brakes hold the arm where it was
            if self._last is None:
                raise RuntimeError(f"no simulated arm pose yet: {err}") from err
            return self._last[0], self._last[1], time.monotonic()
        T_flange, T_tcp = _true_flange_and_tcp(self.kin, st["q"], st["tcp_pose"],
                                               st["tcp_offset"])
        self._last = (T_flange, T_tcp)
        return T_flange, T_tcp, float(st["host_monotonic_s"])

    def protective_stop(self, reason: str) -> None:
        if self.ctl is None:
            raise RuntimeError("the simulated controller is not running")
        self.ctl.protective_stop()

    def start_controller(self) -> None:
        if self.ctl is not None and self.ctl.alive:
            raise RuntimeError(f"a simulated controller already runs on {self.host}")
        if self.ctl is not None:
            self.ctl.close()
        self.ctl = ControllerProcess(self.host)

    def kill_controller(self) -> None:
        if self.ctl is not None and self.ctl.alive:
            self.ctl.kill()

    def freeze_controller(self, frozen: bool) -> None:
        if self.ctl is None or not self.ctl.alive:
            raise RuntimeError("the simulated controller is not running")
        os.kill(self.ctl.pid, signal.SIGSTOP if frozen else signal.SIGCONT)

    def close(self) -> None:
        if self.ctl is not None:
            self.ctl.close()


class _SimWorld:
    """Ground truth and fault switches over the simulated arm and camera."""

    def __init__(self, truth: _EngineTruth | _ProcessTruth, camera: SimCamera,
                 gripper: FakeGripper | None = None, world: str = "ideal",
                 effects: sim_truth.SimEffects = sim_truth.IDEAL_EFFECTS) -> None:
        self._truth = truth
        self._camera = camera
        self._gripper = gripper
        self._world = world
        self._effects = effects

    def truth_values(self) -> sim_truth.SimTruthValues:
        return sim_truth.SimTruthValues(self._world, self._camera.camera,
                                        self._camera.T_flange_camera.copy(), self._effects)

    def true_T_base_target(self, at_s: float | None = None) -> Matrix4:
        return self._camera.target_at(time.monotonic() if at_s is None else at_s)

    def true_T_base_tcp(self) -> Matrix4:
        return self._truth.flange_and_tcp()[1]

    def true_tcp_sample(self) -> tuple[Matrix4, float]:
        _, T_tcp, t_s = self._truth.flange_and_tcp()
        return T_tcp, t_s

    def set_target(self, T_base_target: Matrix4, velocity_mm_s: NDArray[np.float64] | None = None,
                   angular_velocity_rad_s: NDArray[np.float64] | None = None) -> None:
        self._camera.set_target_pose(T_base_target, velocity_mm_s, angular_velocity_rad_s)

    def set_tool_board(self, T_flange_board: Matrix4 | None) -> None:
        """Clamp the calibration plate to the tool (None: take it off); fixed cameras only."""
        if not isinstance(self._camera, FixedSimCamera):
            raise RuntimeError("only a simulated fixed camera sees a plate on the tool")
        self._camera.set_tool_board(T_flange_board)

    def set_camera_blocked(self, blocked: bool) -> None:
        self._camera.set_blocked(blocked)

    def trigger_protective_stop(self, reason: str = "test") -> None:
        self._truth.protective_stop(reason)

    def set_camera_lost(self, lost: bool) -> None:
        self._camera.set_lost(lost)

    def kill_controller(self) -> None:
        self._process_truth().kill_controller()

    def freeze_controller(self, frozen: bool) -> None:
        self._process_truth().freeze_controller(frozen)

    def inject_gripper_fault(self, fault: LineFault, count: int = 1) -> None:
        if self._gripper is None:
            raise RuntimeError("this simulated cell has no simulated gripper")
        self._gripper.inject_line_fault(fault, count)

    def start_controller(self) -> None:
        self._process_truth().start_controller()

    def _process_truth(self) -> _ProcessTruth:
        if not isinstance(self._truth, _ProcessTruth):
            raise RuntimeError("the in-process simulated arm has no controller to restart")
        return self._truth


def _pose_source(truth: _EngineTruth | _ProcessTruth) -> PoseSource:
    """``(T_base_flange, time.monotonic())`` of the simulated arm: where the camera really is."""

    def source() -> tuple[Matrix4, float]:
        T_flange, _, t = truth.flange_and_tcp()
        return T_flange, t

    return source


def _make_camera(config: CellConfig, truth: _EngineTruth | _ProcessTruth | None
                 ) -> tuple[Camera, SimCamera | None]:
    """The configured camera; a simulated one renders what the simulated arm's camera sees."""
    cc, sim = config.camera, config.sim
    if cc.kind == "sim":
        if truth is None:
            raise ConfigError(SIM_CAMERA_NEEDS_SIM_ARM)
        sim_camera: SimCamera
        if config.fixed_camera:
            sim_camera = _fixed_sim_camera(config, truth)
        else:
            true = sim_truth.resolve(config)
            fx = true.effects
            sim_camera = SimCamera(
                true.camera, config.target.model(), sim.T_base_target.T(), true.T_flange_camera,
                _pose_source(truth), reported_camera=sim_truth.factory_calibration(config),
                fps=cc.fps, noise_std=sim.noise_std, blur_sigma_px=sim.blur_sigma_px,
                exposure_jitter=fx.gain_jitter,
                latency_s=fx.camera_latency_s, latency_jitter_s=fx.camera_latency_jitter_s,
                timestamp_offset_s=fx.timestamp_offset_s,
                timestamp_jitter_s=fx.timestamp_jitter_s, motion_blur=fx.motion_blur,
                flicker_depth=fx.flicker_depth, flicker_hz=fx.flicker_hz)
        if cc.exposure_us is not None or cc.iso is not None or cc.focus is not None:
            try:
                sim_camera.apply_settings(CameraSettings(cc.exposure_us, cc.iso, cc.focus))
            except ValueError as err:
                raise ConfigError(f"camera: {err}") from err
        return sim_camera, sim_camera
    from drivers.oak.camera import OakCamera

    return OakCamera(oak_settings(config)), None


SIM_CAMERA_NEEDS_SIM_ARM = ("camera.kind = \"sim\" needs a simulated robot (robot.kind = "
                            "\"sim\" or sim.ur_controller = true)")
ROBOTIQ_NEEDS_PORT = "gripper.port: a serial device is needed for kind = \"robotiq\""


def hardware_problems(config: CellConfig) -> list[Problem]:
    """Every reason :func:`build_hardware` would refuse this config, found without building
    or touching anything: the same rules, so ``cell config check`` fails on what ``cell serve``
    refuses."""
    problems: list[Problem] = []
    cc = config.camera
    if cc.kind == "sim":
        if config.robot.kind == "ur" and not config.sim.ur_controller:
            problems.append(Problem("camera.kind", SIM_CAMERA_NEEDS_SIM_ARM))
        if cc.exposure_us is not None or cc.iso is not None or cc.focus is not None:
            try:
                SimCamera.check_settings(CameraSettings(cc.exposure_us, cc.iso, cc.focus),
                                         cc.fps)
            except ValueError as err:
                problems.append(Problem("camera", str(err)))
    else:
        try:
            oak_settings(config)
        except ConfigError as err:
            problems.append(Problem("camera", str(err)))
    if config.gripper.kind == "robotiq" and not config.gripper.port:
        problems.append(Problem("gripper.port", ROBOTIQ_NEEDS_PORT))
    return problems


def _fixed_sim_camera(config: CellConfig, truth: _EngineTruth | _ProcessTruth
                      ) -> FixedSimCamera:
    """The simulated fixed camera at its true pose, watching the simulated arm's tool."""
    sim, true = config.sim, sim_truth.resolve(config)
    return FixedSimCamera(
        true.camera, config.target.model(), sim.T_base_target.T(), true.T_flange_camera,
        _pose_source(truth), config.tool.T_flange_tcp.T(), tool_radius_mm=sim.tool_radius_mm,
        reported_camera=sim_truth.factory_calibration(config),
        T_flange_board=None if sim.T_flange_board is None else sim.T_flange_board.T(),
        fps=config.camera.fps, noise_std=sim.noise_std, blur_sigma_px=sim.blur_sigma_px)


def oak_settings(config: CellConfig) -> OakSettings:
    """The OAK adapter's settings from ``[camera]``; unset sensor values keep its defaults."""
    from drivers.oak.camera import OakSettings

    cc = config.camera
    sensor: dict[str, Any] = {}
    if cc.exposure_us is not None:
        sensor["exposure_us"] = cc.exposure_us
    if cc.iso is not None:
        sensor["iso"] = cc.iso
    try:
        return OakSettings(width=cc.width, height=cc.height, fps=cc.fps, socket=cc.socket,
                           device_id=cc.device_id or None, focus=cc.focus, **sensor)
    except ValueError as err:
        raise ConfigError(f"camera: {err}") from err


def robotiq_gripper(config: CellConfig, port: str) -> RobotiqGripper:
    """The Modbus RTU adapter with ``[gripper]``'s link and timing settings."""
    gc = config.gripper
    return RobotiqGripper(port, slave_id=gc.slave_id, baudrate=gc.baudrate,
                          timeout_s=gc.timeout_s, retries=gc.retries,
                          motion_timeout_s=gc.motion_timeout_s,
                          activation_timeout_s=gc.activation_timeout_s)


def build_camera(config: CellConfig) -> tuple[Camera, Callable[[], None]]:
    """Only the camera, for commissioning commands, and a function that releases it.

    A simulated camera needs a simulated arm to hang on: it gets an in-process one at the
    configured home pose, so it shows what the simulated cell sees at home.
    """
    truth = None
    engine = None
    if config.camera.kind == "sim":
        home_rad = [float(v) for v in np.radians(config.robot.home_joints_deg)]
        engine = MotionEngine(q_rad=home_rad)
        truth = _EngineTruth(engine, true_kinematics(config))
    try:
        camera, _ = _make_camera(config, truth)
    except BaseException:
        if engine is not None:
            engine.close()
        raise

    def release() -> None:
        camera.disconnect()
        if engine is not None:
            engine.close()

    return camera, release


def all_simulated(config: CellConfig) -> bool:
    """True when the config builds only fakes (then the sample API tokens are allowed)."""
    return not config.has_real_device()


def build_hardware(config: CellConfig) -> Hardware:
    """Create (not connect) the devices the config names; Cell.start connects them."""
    closers: list[Callable[[], None]] = []
    try:
        return _build(config, closers)
    except BaseException:
        for close in reversed(closers):
            with contextlib.suppress(Exception):  # cleaning up after a failed build
                close()
        raise


def _build(config: CellConfig, closers: list[Callable[[], None]]) -> Hardware:
    rc, sim = config.robot, config.sim
    truth: _EngineTruth | _ProcessTruth | None = None
    arm: Arm
    if rc.kind == "sim":
        engine = MotionEngine(q_rad=[float(v) for v in np.radians(rc.home_joints_deg)])
        closers.append(engine.close)
        truth = _EngineTruth(engine, true_kinematics(config))
        arm = SimArm(engine)
        closers.append(arm.disconnect)
    else:
        if sim.ur_controller:
            process_truth = _ProcessTruth(rc.host, start=sim.controller_running_at_start,
                                          kin=true_kinematics(config))
            closers.append(process_truth.close)
            truth = process_truth
        from drivers.ur.adapter import URArm

        arm = URArm(rc.host, connect_timeout_s=rc.connect_timeout_s,
                    call_timeout_s=rc.call_timeout_s, watchdog_s=rc.watchdog_s,
                    stale_after_s=rc.stale_after_s)
        closers.append(arm.disconnect)

    camera, sim_camera = _make_camera(config, truth)
    closers.append(camera.disconnect)

    gripper: Gripper | None = None
    fake: FakeGripper | None = None
    gc = config.gripper
    if gc.kind == "sim":
        fake = FakeGripper(slave_id=gc.slave_id, object_width_mm=sim.gripper_object_width_mm,
                           activation_time_s=0.2)
        fake.start()
        closers.append(fake.stop)
        gripper = robotiq_gripper(config, fake.port)
        closers.append(gripper.disconnect)
    elif gc.kind == "robotiq":
        if not gc.port:
            raise ConfigError(ROBOTIQ_NEEDS_PORT)
        gripper = robotiq_gripper(config, gc.port)
        closers.append(gripper.disconnect)

    simulated = all_simulated(config)
    world = None
    if simulated and truth is not None and sim_camera is not None:
        world = _SimWorld(truth, sim_camera, fake, config.sim.world,
                          sim_truth.effects(config))
    hw = Hardware(arm=arm, camera=camera, gripper=gripper, simulated=simulated, sim=world,
                  closers=list(closers))
    closers.clear()
    return hw

