"""Build the simulated devices of one cell from a :class:`~fakes.sim_cell.spec.SimCellSpec`:
the arm (its engine here, or the simulated controller in its own process), the world's parts,
the camera that sees them from where that arm really is, the gripper (on a TCP relay or a
pseudo-terminal) that closes on them where the arm really is, and the world over them.
"""

from __future__ import annotations

import contextlib
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any, Generic

from fakes.fixed_camera import FixedSimCamera
from fakes.gripper import FakeGripper
from fakes.parts import SimParts
from fakes.sim_arm import SimArm
from fakes.sim_camera import PoseSource, SimCamera
from fakes.sim_cell.arm_truth import ArmTruth, EngineTruth, Matrix4, ProcessTruth
from fakes.sim_cell.grasp import PartsGrasp
from fakes.sim_cell.spec import ArmSpec, CameraSpec, GripperSpec, PartsSpec, SimCellSpec
from fakes.sim_cell.world import SimulatedWorld, TruthT
from fakes.ur_sim.engine import MotionEngine


@dataclass
class SimulatedCell(Generic[TruthT]):
    """What :func:`build_sim_cell` built; :meth:`close` releases all of it.

    ``arm`` is the in-process arm (None with the controller in its own process: the real UR
    adapter drives that one over the wire); ``gripper`` serves on ``gripper.port``, where the
    real Modbus RTU adapter drives it; ``world`` exists with a simulated arm and camera.
    """

    arm: SimArm | None = None
    parts: SimParts | None = None
    camera: SimCamera | None = None
    gripper: FakeGripper | None = None
    world: SimulatedWorld[TruthT] | None = None
    closers: list[Callable[[], None]] = field(default_factory=list)
    readiness: list[Callable[[], None]] = field(default_factory=list)

    def wait_ready(self) -> None:
        """Block until the simulated devices in processes of their own (the controller)
        listen: they boot while the service starts, and its first connect waits here."""
        for wait in self.readiness:
            wait()

    def close(self) -> None:
        """Release in reverse order of creation; never raises."""
        for close in reversed(self.closers):
            with contextlib.suppress(Exception):  # shutdown goes on whatever one part does
                close()
        self.closers.clear()


def build_sim_cell(spec: SimCellSpec, truth: TruthT | None) -> SimulatedCell[TruthT]:
    """The simulated devices ``spec`` names, and the world over them described by ``truth``
    (None: no world, the devices alone). A camera needs an arm to hang on and parts to see
    (ValueError without them); the gripper closes on the parts where the arm is (on nothing
    without either)."""
    built = SimulatedCell[TruthT]()
    try:
        arm_truth = _arm(spec.arm, built) if spec.arm is not None else None
        built.parts = _parts(spec.parts) if spec.parts is not None else None
        if spec.camera is not None:
            if arm_truth is None:
                raise ValueError("a simulated camera needs a simulated arm to hang on")
            if built.parts is None:
                raise ValueError("a simulated camera needs the world's parts to see")
            built.camera = _camera(spec.camera, built.parts, arm_truth)
            built.closers.append(built.camera.disconnect)
        if spec.gripper is not None:
            grasp = (PartsGrasp(built.parts, arm_truth)
                     if built.parts is not None and arm_truth is not None else None)
            built.gripper = _gripper(spec.gripper, grasp)
            built.closers.append(built.gripper.stop)
        if (truth is not None and arm_truth is not None and built.camera is not None
                and built.parts is not None):
            built.world = SimulatedWorld(arm_truth, built.camera, built.parts, built.gripper,
                                         truth)
        return built
    except BaseException:
        built.close()
        raise


def _arm(spec: ArmSpec, built: SimulatedCell[TruthT]) -> ArmTruth:
    kin = spec.true_kinematics()
    if spec.controller_host is not None:
        truth = ProcessTruth(spec.controller_host, start=spec.controller_running_at_start,
                             kin=kin)
        built.closers.append(truth.close)
        built.readiness.append(truth.wait_ready)
        return truth
    engine = MotionEngine(q_rad=list(spec.home_joints_rad))
    built.closers.append(engine.close)
    built.arm = SimArm(engine)
    built.closers.append(built.arm.disconnect)
    return EngineTruth(engine, kin)


def _flange_source(arm: ArmTruth) -> PoseSource:
    """``(T_base_flange, time.monotonic())`` of the simulated arm: where the camera really is."""

    def source() -> tuple[Matrix4, float]:
        T_flange, _, t_s = arm.flange_and_tcp()
        return T_flange, t_s

    return source


def _parts(spec: PartsSpec) -> SimParts:
    return SimParts.one(spec.layout, spec.T_base_part, spec.width_mm)


def _camera(spec: CameraSpec, parts: SimParts, arm: ArmTruth) -> SimCamera:
    fx = spec.effects
    sensor: dict[str, Any] = dict(
        reported_camera=spec.reported_lens, fps=spec.fps, noise_std=spec.noise_std,
        blur_sigma_px=spec.blur_sigma_px, exposure_jitter=fx.gain_jitter,
        latency_s=fx.latency_s, latency_jitter_s=fx.latency_jitter_s,
        timestamp_offset_s=fx.timestamp_offset_s, timestamp_jitter_s=fx.timestamp_jitter_s,
        motion_blur=fx.motion_blur, flicker_depth=fx.flicker_depth, flicker_hz=fx.flicker_hz)
    if spec.fixed is not None:
        return FixedSimCamera(
            spec.lens, parts, spec.T_mount, _flange_source(arm),
            spec.fixed.T_flange_tcp, tool_radius_mm=spec.fixed.tool_radius_mm,
            T_flange_board=spec.fixed.T_flange_board, **sensor)
    return SimCamera(spec.lens, parts, spec.T_mount, _flange_source(arm), **sensor)


def _gripper(spec: GripperSpec, grasp: PartsGrasp | None) -> FakeGripper:
    gripper = FakeGripper(slave_id=spec.slave_id, grasp=grasp,
                          activation_time_s=spec.activation_time_s, transport=spec.transport)
    gripper.start()
    return gripper
