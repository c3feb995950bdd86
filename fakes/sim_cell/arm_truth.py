"""Where the simulated arm really is: read from its engine in this process, or from the
simulated controller in its own process; with a true geometry of its own, off the nominal DH
table the controller reports with."""

from __future__ import annotations

import os
import signal
import time
from typing import Any, Protocol

import numpy as np
from numpy.typing import NDArray

from estimator.transforms import T_from_ur_pose, invert_T
from fakes.ur_controller.process import ControllerProcess
from fakes.ur_sim.engine import MotionEngine
from fakes.ur_sim.kinematics import UR5eKinematics

Matrix4 = NDArray[np.float64]


class ArmTruth(Protocol):
    """The simulated arm's true state, and the safety stop a test can trigger on it."""

    def flange_and_tcp(self) -> tuple[Matrix4, Matrix4, float]:
        """``(T_base_flange, T_base_tcp, time.monotonic())`` where the arm really is."""
        ...

    def protective_stop(self, reason: str) -> None: ...


def true_flange_and_tcp(kin: UR5eKinematics | None, q: Any, tcp_pose: Any, tcp_offset: Any
                        ) -> tuple[Matrix4, Matrix4]:
    """``(T_base_flange, T_base_tcp)`` where the arm really is: the controller's report
    (nominal kinematics) or, with a true geometry, its forward kinematics at the joints."""
    T_flange_tcp = T_from_ur_pose(tcp_offset)
    if kin is None:
        T_tcp = T_from_ur_pose(tcp_pose)
        return T_tcp @ invert_T(T_flange_tcp), T_tcp
    T_flange = kin.forward(q)
    return T_flange, T_flange @ T_flange_tcp


class EngineTruth:
    """The true state of an arm whose engine runs in this process."""

    def __init__(self, engine: MotionEngine, kin: UR5eKinematics | None = None) -> None:
        self.engine = engine
        self.kin = kin

    def flange_and_tcp(self) -> tuple[Matrix4, Matrix4, float]:
        snap = self.engine.snapshot()
        T_flange, T_tcp = true_flange_and_tcp(self.kin, snap.q, snap.tcp_pose, snap.tcp_offset)
        return T_flange, T_tcp, snap.host_monotonic_s

    def protective_stop(self, reason: str) -> None:
        self.engine.trigger_protective_stop(reason)


class ProcessTruth:
    """The same, from a simulated controller in its own process (over its control channel).

    ur_rtde's constructors hold the GIL while talking to the controller, so a controller in
    the client's process would deadlock; time.monotonic is system-wide, so its timestamps
    compare with ours. The controller can be killed and started again (a controller reboot):
    meanwhile the arm stands where it was, so the last pose read stays the truth.
    """

    def __init__(self, host: str, start: bool, kin: UR5eKinematics | None = None) -> None:
        self.host = host
        self.kin = kin
        self.ctl: ControllerProcess | None = (ControllerProcess(host, wait=False) if start
                                              else None)
        self._last: tuple[Matrix4, Matrix4] | None = None

    def wait_ready(self) -> None:
        """Block until the controller started with this truth listens (it boots meanwhile)."""
        if self.ctl is not None:
            self.ctl.wait_ready()

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
        T_flange, T_tcp = true_flange_and_tcp(self.kin, st["q"], st["tcp_pose"],
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
