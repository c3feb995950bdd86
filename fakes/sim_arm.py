"""An in-process simulated UR5e behind :class:`drivers.arm.Arm`, for fast cell tests.

It drives the same :class:`fakes.ur_sim.MotionEngine` as the simulated controller's protocol
servers, minus the network: motion takes real time, limits and safety stops behave the same,
and errors come out as ``drivers.errors`` types exactly as the ``ur_rtde`` adapter raises them.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager

import numpy as np
from numpy.typing import NDArray

from drivers.arm import ArmState, JogFrame, speedl_accel
from drivers.errors import (
    ConnectionLostError,
    DriverError,
    EmergencyStopError,
    MotionError,
    NotReadyError,
    ProtectiveStopError,
    UnlockTooEarlyError,
)
from estimator.transforms import T_from_ur_pose, ur_pose_from_T
from fakes.ur_sim.engine import (
    CommandOutcome,
    CommandRejectedError,
    EmergencyStopActiveError,
    EngineError,
    EngineSnapshot,
    MotionEngine,
    NotRunningError,
    ProtectiveStopActiveError,
    RobotMode,
    SafetyMode,
    SimLimits,
)

_MOVE_TIMEOUT_S = 300.0  # a blocking move never waits longer than this


@contextmanager
def _driver_errors() -> Iterator[None]:
    """Translate the engine's refusals into the arm interface's error types."""
    try:
        yield
    except ProtectiveStopActiveError as err:
        raise ProtectiveStopError(str(err)) from err
    except EmergencyStopActiveError as err:
        raise EmergencyStopError(str(err)) from err
    except NotRunningError as err:
        raise NotReadyError(str(err)) from err
    except CommandRejectedError as err:
        raise MotionError(str(err)) from err
    except EngineError as err:
        raise DriverError(str(err)) from err


class SimArm:
    """``drivers.arm.Arm`` on an in-process motion engine.

    ``jog_watchdog_s`` plays the adapter's watchdog: a jog not re-sent within it brakes.
    """

    def __init__(
        self, engine: MotionEngine | None = None, *, q_rad: list[float] | None = None,
        limits: SimLimits | None = None, jog_watchdog_s: float = 0.25,
        power_timeout_s: float = 10.0,
    ) -> None:
        self._own_engine = engine is None
        self.engine = engine if engine is not None else MotionEngine(q_rad, limits)
        self.jog_watchdog_s = jog_watchdog_s
        self.power_timeout_s = power_timeout_s
        self._connected = False
        self._last_move: int | None = None  # the engine's id of the last move sent

    def close(self) -> None:
        """Disconnect, and stop the engine if this arm created it."""
        self.disconnect()
        if self._own_engine:
            self.engine.close()

    # -- connection and power ---------------------------------------------------------------
    def connect(self) -> None:
        if not self.engine.alive:
            raise ConnectionLostError("the simulated controller has been shut down")
        self._connected = True

    def disconnect(self) -> None:
        if self._connected:
            self.engine.stop_l()
        self._connected = False

    def _require_connected(self) -> None:
        if not self._connected:
            raise ConnectionLostError("not connected to the simulated arm: call connect()")

    def power_on(self) -> None:
        """Power on and release the brakes; returns when RUNNING (NotReadyError on timeout)."""
        self._require_connected()
        with _driver_errors():
            self.engine.brake_release()
        if not self._wait(lambda s: s.robot_mode == RobotMode.RUNNING, self.power_timeout_s):
            raise NotReadyError("the arm did not reach RUNNING after power on")

    def power_off(self) -> None:
        self._require_connected()
        if self.engine.snapshot().moving:
            raise NotReadyError("power off refused: the arm is moving; stop it first")
        self.engine.power_off()

    def _wait(self, pred: Callable[[EngineSnapshot], bool], timeout_s: float) -> bool:
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            if pred(self.engine.snapshot()):
                return True
            time.sleep(0.01)
        return pred(self.engine.snapshot())

    def set_tcp(self, T_flange_tcp: NDArray[np.float64]) -> None:
        self._require_connected()
        with _driver_errors():
            self.engine.set_tcp(ur_pose_from_T(T_flange_tcp))

    # -- state -----------------------------------------------------------------------------
    def state(self) -> ArmState:
        s = self.engine.snapshot()
        return ArmState(
            connected=self._connected,
            robot_mode=s.robot_mode.name if self._connected else "DISCONNECTED",
            safety_status=s.safety_mode.name,
            moving=s.moving,
            T_base_tcp=T_from_ur_pose(s.tcp_pose),
            joints_rad=np.array(s.q),
            timestamp_s=s.host_monotonic_s,
        )

    def tcp_pose(self) -> NDArray[np.float64]:
        self._require_connected()
        return T_from_ur_pose(self.engine.snapshot().tcp_pose)

    def joint_positions_rad(self) -> NDArray[np.float64]:
        self._require_connected()
        return np.array(self.engine.snapshot().q)

    def forward_kinematics(self, joints_rad: NDArray[np.float64]) -> NDArray[np.float64]:
        q = np.asarray(joints_rad, dtype=float).reshape(-1)
        with _driver_errors():
            return T_from_ur_pose(self.engine.fk(q.tolist()))

    def pose_at(self, timestamp_s: float) -> NDArray[np.float64]:
        """``T_base_tcp`` at a past monotonic instant (joint history, FK with today's TCP)."""
        q = self.engine.joints_at(timestamp_s)
        return T_from_ur_pose(self.engine.fk(q.tolist()))

    def is_moving(self) -> bool:
        return self.engine.snapshot().moving

    # -- motion ----------------------------------------------------------------------------
    def move_linear(
        self, T_base_tcp: NDArray[np.float64], speed_mm_s: float, accel_mm_s2: float,
        wait: bool = True,
    ) -> None:
        self._require_connected()
        with _driver_errors():
            cid = self._last_move = self.engine.move_l(
                ur_pose_from_T(T_base_tcp), speed_mm_s / 1000.0, accel_mm_s2 / 1000.0)
        if wait:
            self._await(cid)

    def move_joint(
        self, joints_rad: NDArray[np.float64], speed_rad_s: float, accel_rad_s2: float,
        wait: bool = True,
    ) -> None:
        self._require_connected()
        with _driver_errors():
            cid = self._last_move = self.engine.move_j(
                list(np.asarray(joints_rad, dtype=float).reshape(-1)), speed_rad_s, accel_rad_s2)
        if wait:
            self._await(cid)

    def wait_for_motion(self, timeout_s: float | None = None) -> None:
        if self._last_move is not None:
            self._await(self._last_move, _MOVE_TIMEOUT_S if timeout_s is None else timeout_s)

    def _await(self, cid: int, timeout_s: float = _MOVE_TIMEOUT_S) -> None:
        outcome = self.engine.wait_for(cid, timeout_s)
        if outcome == CommandOutcome.SUCCEEDED:
            return
        self.engine.wait_until_idle(5.0)  # report once the safety stop has braked to rest
        s = self.engine.snapshot()
        if s.safety_mode == SafetyMode.PROTECTIVE_STOP:
            raise ProtectiveStopError(f"move ended by a protective stop: {s.last_stop_reason}")
        if s.safety_mode in (SafetyMode.ROBOT_EMERGENCY_STOP, SafetyMode.SYSTEM_EMERGENCY_STOP):
            raise EmergencyStopError("move ended by an emergency stop")
        if outcome == CommandOutcome.RUNNING:
            raise MotionError(f"move did not finish within {_MOVE_TIMEOUT_S:.0f} s")
        raise MotionError(f"move did not complete ({outcome.value})")

    def jog(
        self, velocity: NDArray[np.float64], frame: JogFrame = "base",
        accel_mm_s2: float = 500.0,
    ) -> None:
        self._require_connected()
        v = np.asarray(velocity, dtype=float).reshape(-1)
        if v.shape != (6,):
            raise MotionError("jog velocity must be [vx, vy, vz, wx, wy, wz]")
        speeds = [*(v[:3] / 1000.0).tolist(), *v[3:].tolist()]
        with _driver_errors():
            self.engine.jog_start(speeds, frame, accel_mm_s2 / 1000.0, self.jog_watchdog_s)

    def servo_twist(
        self, velocity: NDArray[np.float64], accel_mm_s2: float, watchdog_s: float,
        angular_accel_rad_s2: float | None = None,
    ) -> None:
        """Base-frame twist on the engine's speedl; it brakes by itself after ``watchdog_s``.
        speedl has one acceleration (m/s^2 and, as aRot, rad/s^2): the larger of the two."""
        self._require_connected()
        v = np.asarray(velocity, dtype=float).reshape(-1)
        if v.shape != (6,) or not np.all(np.isfinite(v)):
            raise MotionError("servo twist must be 6 finite values [vx, vy, vz, wx, wy, wz]")
        speeds = [*(v[:3] / 1000.0).tolist(), *v[3:].tolist()]
        with _driver_errors():
            self.engine.speed_l(speeds, speedl_accel(accel_mm_s2, angular_accel_rad_s2),
                                watchdog_s)

    def stop(self, decel_mm_s2: float = 2000.0) -> None:
        with _driver_errors():
            self.engine.stop_l(max(decel_mm_s2, 1.0) / 1000.0)

    def recover_protective_stop(self) -> None:
        """Unlock; UnlockTooEarlyError while the controller still refuses (first 5 s)."""
        self._require_connected()
        s = self.engine.snapshot()
        if s.safety_mode in (SafetyMode.ROBOT_EMERGENCY_STOP, SafetyMode.SYSTEM_EMERGENCY_STOP):
            raise EmergencyStopError("an emergency stop needs a person at the cell")
        if not self.engine.unlock_protective_stop():
            since = s.seconds_since_protective_stop or 0.0
            wait_s = max(0.0, self.engine.limits.unlock_delay_s - since)
            raise UnlockTooEarlyError(
                f"unlock refused: the controller allows it {wait_s:.1f} s from now", wait_s)
