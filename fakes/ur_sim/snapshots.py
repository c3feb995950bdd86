"""The arm's state as RTDE reports it: one consistent :class:`EngineSnapshot` per cycle.

The protocol layer asks for the state several times a cycle and a standing arm's state does
not change for seconds, so snapshots and the TCP kinematics behind them are cached on
exactly what they depend on; the kinematics are most of a cycle's cost at 500 Hz.
"""

from __future__ import annotations

import math

import numpy as np

from estimator.transforms import ur_pose_from_T
from fakes.ur_sim.arm_core import ArmCore
from fakes.ur_sim.state import (
    EngineSnapshot,
    RobotMode,
    RobotStatusBit,
    SafetyMode,
    SafetyStatusBit,
    Vec,
)

Floats = tuple[float, ...]  # a pose or twist as a snapshot carries it

_JOINT_RUNNING, _JOINT_IDLE, _JOINT_POWER_OFF = 253, 255, 239
_POWERED = (RobotMode.POWER_ON, RobotMode.IDLE, RobotMode.RUNNING)
_SAFETY_BITS = {
    SafetyMode.NORMAL: (SafetyStatusBit.NORMAL_MODE,),
    SafetyMode.REDUCED: (SafetyStatusBit.REDUCED_MODE,),
    SafetyMode.PROTECTIVE_STOP: (SafetyStatusBit.PROTECTIVE_STOPPED,
                                 SafetyStatusBit.STOPPED_DUE_TO_SAFETY),
    SafetyMode.RECOVERY: (SafetyStatusBit.RECOVERY_MODE,),
    SafetyMode.SAFEGUARD_STOP: (SafetyStatusBit.SAFEGUARD_STOPPED,
                                SafetyStatusBit.STOPPED_DUE_TO_SAFETY),
    SafetyMode.SYSTEM_EMERGENCY_STOP: (SafetyStatusBit.SYSTEM_EMERGENCY_STOPPED,
                                       SafetyStatusBit.EMERGENCY_STOPPED,
                                       SafetyStatusBit.STOPPED_DUE_TO_SAFETY),
    SafetyMode.ROBOT_EMERGENCY_STOP: (SafetyStatusBit.ROBOT_EMERGENCY_STOPPED,
                                      SafetyStatusBit.EMERGENCY_STOPPED,
                                      SafetyStatusBit.STOPPED_DUE_TO_SAFETY),
    SafetyMode.VIOLATION: (SafetyStatusBit.VIOLATION, SafetyStatusBit.STOPPED_DUE_TO_SAFETY),
    SafetyMode.FAULT: (SafetyStatusBit.FAULT, SafetyStatusBit.STOPPED_DUE_TO_SAFETY),
}


class SnapshotBuilder:
    """Builds (and caches) snapshots of one arm; callers hold the engine lock."""

    def __init__(self, core: ArmCore) -> None:
        self._core = core
        self._snap_cache: tuple[tuple[object, ...], EngineSnapshot] | None = None
        # (joints, speeds, TCP offset) -> TCP pose and speed (see tcp_state)
        self._tcp_cache: tuple[tuple[object, ...], Floats, Floats] | None = None

    def snapshot(self) -> EngineSnapshot:
        core = self._core
        # While moving, the state belongs to the last control cycle, not to the reading instant.
        core.sync_idle_clock()
        # One snapshot per cycle and state: the protocol layer asks several times a cycle.
        key = (core.clock.cycles, core.next_id, id(core.cmd), core.safety_mode,
               core.robot_mode, core.program_running, core.speed_fraction,
               tuple(core.tcp_offset), core.stop_reason, core.q.tobytes(), core.qd.tobytes())
        if self._snap_cache is not None and self._snap_cache[0] == key:
            return self._snap_cache[1]
        snap = self._build()
        self._snap_cache = (key, snap)
        return snap

    def tcp_state(self, q: Vec, qd: Vec) -> tuple[Floats, Floats]:
        """TCP pose (UR) and speed of joints ``q``, ``qd``: the kinematics are most of a
        cycle's cost, so a standing arm's are computed once, not 500 times a second."""
        core = self._core
        key = (q.tobytes(), qd.tobytes(), tuple(core.tcp_offset))
        cached = self._tcp_cache
        if cached is not None and cached[0] == key:
            return cached[1], cached[2]
        pose = tuple(map(float, ur_pose_from_T(core.kin.forward_tcp(q))))
        twist = core.kin.jacobian_tcp(q) @ qd
        twist[:3] /= 1000.0
        speed = tuple(map(float, twist))
        self._tcp_cache = (key, pose, speed)
        return pose, speed

    def _build(self) -> EngineSnapshot:
        core = self._core
        now = core.now()
        q, qd = core.q, core.qd
        pose, twist = self.tcp_state(q, qd)
        safety = core.safety_mode
        sbits = sum(1 << int(b) for b in _SAFETY_BITS[safety])
        rbits = (1 << RobotStatusBit.POWER_ON) if core.robot_mode in _POWERED else 0
        if core.program_running:
            rbits |= 1 << RobotStatusBit.PROGRAM_RUNNING
        mode = core.robot_mode
        joint_mode = (_JOINT_RUNNING if mode == RobotMode.RUNNING
                      else _JOINT_IDLE if mode in _POWERED else _JOINT_POWER_OFF)
        uptime = now - core.clock.t0
        temps = tuple(25.0 + 8.0 * (1.0 - math.exp(-uptime / 600.0)) + 0.5 * i
                      for i in range(6)) if mode in _POWERED else (25.0,) * 6
        cmd = core.cmd
        stopped = safety != SafetyMode.NORMAL
        return EngineSnapshot(
            timestamp_s=uptime,
            host_monotonic_s=now,
            q=tuple(map(float, q)),
            qd=tuple(map(float, qd)),
            target_q=tuple(map(float, q)),
            target_qd=tuple(map(float, qd)),
            target_qdd=tuple(map(float, core.qdd)),
            tcp_pose=pose,
            tcp_speed=twist,
            target_tcp_pose=pose,
            target_tcp_speed=twist,
            tcp_offset=tuple(core.tcp_offset),
            tcp_force=(0.0,) * 6,
            joint_temperatures_c=temps,
            actual_current_a=tuple(float(0.3 * a) for a in core.qdd),
            joint_modes=(joint_mode,) * 6,
            robot_mode=mode,
            safety_mode=safety,
            safety_status_bits=sbits,
            robot_status_bits=rbits,
            moving=bool(cmd is not None or np.any(qd)),
            active_command=cmd.name if cmd is not None else None,
            async_progress=cmd.progress if cmd is not None else -1,
            speed_scaling=0.0 if stopped else core.speed_fraction,
            target_speed_fraction=core.speed_fraction,
            seconds_since_protective_stop=(
                now - core.stop_t if safety == SafetyMode.PROTECTIVE_STOP
                and core.stop_t is not None else None),
            last_stop_reason=core.stop_reason,
            last_command_id=core.next_id - 1,
        )
