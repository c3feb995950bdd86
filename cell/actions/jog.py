"""Jogging: Cartesian steps, and continuous jogs held by a dead-man heartbeat.

A step is one guarded linear move about the TCP (base or tool frame), capped by
``limits.max_jog_step_mm`` / ``max_jog_step_deg`` and the jog speed limits. A continuous jog
re-sends its twist every 20 ms through the guarded arm, which checks it each time against the
caps and the path ``JOG_HORIZON_S`` ahead; it ends when heartbeats stop for
``limits.deadman_timeout_s``, on stop, on a limit, or when the arm is no longer ready.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from cell.core import CellCore
from cell.error_codes import ErrorCode
from cell.errors import CellError, RefusedError
from cell.motion.guard import Motion
from cell.vision.frames import step_goal
from drivers.arm import JogFrame
from drivers.errors import DriverError

Matrix4 = NDArray[np.float64]
JOG_PERIOD_S = 0.02


@dataclass
class _Jog:
    motion: Motion
    velocity: NDArray[np.float64]  # [vx, vy, vz mm/s, wx, wy, wz rad/s]
    frame: JogFrame
    last_heartbeat_s: float
    thread: threading.Thread | None = None
    stopped_reason: str = ""


class Jogger:
    def __init__(self, core: CellCore, stop: Callable[[str, str], object]) -> None:
        """``stop(caller, reason)`` is the cell's one stop path, taken when the dead-man's
        heartbeat expires, exactly as ``/stop`` takes it."""
        self.core = core
        self._stop = stop
        self._jog: _Jog | None = None
        self._lock = threading.Lock()

    def step(self, caller: str, *, frame: JogFrame, translation_mm: ArrayLike,
             rotation_deg: ArrayLike, speed_mm_s: float | None = None) -> Matrix4:
        """A Cartesian step about the TCP in base or tool frame; returns the reached pose."""
        limits = self.core.config.limits
        speed = min(limits.max_jog_speed_mm_s, 50.0) if speed_mm_s is None else float(speed_mm_s)
        accel = min(500.0, limits.max_accel_mm_s2)
        t = np.asarray(translation_mm, dtype=float).reshape(-1)
        r = np.asarray(rotation_deg, dtype=float).reshape(-1)
        params = {"frame": frame, "translation_mm": t.tolist(), "rotation_deg": r.tolist(),
                  "speed_mm_s": speed}
        arm = self.core.arm
        with self.core.audit.command(caller, "jog_step", params):
            arm.guard.check_jog_step(t, r, speed)
            with self.core.slot.hold("jog_step"):
                st = arm.ready_state()
                goal = step_goal(st.T_base_tcp, t, r, frame)
                arm.move_linear(goal, speed, accel, what="jog step")
                return arm.state().T_base_tcp

    def start(self, caller: str, *, frame: JogFrame, linear_mm_s: ArrayLike,
              angular_deg_s: ArrayLike) -> dict[str, Any]:
        """Start (or change) a continuous jog; it runs while heartbeats keep arriving."""
        lin = np.asarray(linear_mm_s, dtype=float).reshape(3)
        ang = np.asarray(angular_deg_s, dtype=float).reshape(3)
        params = {"frame": frame, "linear_mm_s": lin.tolist(), "angular_deg_s": ang.tolist()}
        arm = self.core.arm
        with self.core.audit.command(caller, "jog_start", params):
            arm.guard.check_jog_speed(lin, ang)
            velocity = np.concatenate([lin, np.radians(ang)])
            with self._lock:
                jog = self._jog
                if jog is not None and self.core.slot.current is jog.motion:
                    jog.velocity, jog.frame = velocity, frame
                    jog.last_heartbeat_s = time.monotonic()
                    return self._info(jog)
            motion = self.core.slot.claim("jog")
            jog = _Jog(motion, velocity, frame, time.monotonic())
            try:
                arm.jog(velocity, frame, accel_mm_s2=self._accel())  # checked; first command
            except BaseException:
                self.core.slot.release(motion)
                raise
            # the dead-man runs from the moment the jog is under way: the caller cannot send a
            # heartbeat before this answer, and the first command may take a while to go out
            jog.last_heartbeat_s = time.monotonic()
            jog.thread = threading.Thread(target=self._loop, args=(jog,), name="cell-jog",
                                          daemon=True)
            with self._lock:
                self._jog = jog
            jog.thread.start()
            self.core.events.publish("jog", {"jogging": True, **params})
            return self._info(jog)

    def heartbeat(self, caller: str) -> dict[str, Any]:
        """Dead-man: keeps a continuous jog alive for ``limits.deadman_timeout_s`` more."""
        _ = caller
        with self._lock:
            jog = self._jog
            if jog is None or self.core.slot.current is not jog.motion:
                raise RefusedError(ErrorCode.not_jogging,
                                   "no continuous jog is running (it may have "
                                   "stopped: dead-man expired, stop, or a limit)")
            jog.last_heartbeat_s = time.monotonic()
            return self._info(jog)

    def _accel(self) -> float:
        return min(500.0, self.core.config.limits.max_accel_mm_s2)

    def _info(self, jog: _Jog) -> dict[str, Any]:
        return {"jogging": True, "frame": jog.frame,
                "deadman_timeout_s": self.core.config.limits.deadman_timeout_s}

    def _loop(self, jog: _Jog) -> None:
        core = self.core
        timeout_s = core.config.limits.deadman_timeout_s
        reason = "stopped"
        try:
            while True:
                time.sleep(JOG_PERIOD_S)
                if jog.motion.cancel.is_set():
                    reason = "stop requested" if jog.motion.reason is None \
                        else jog.motion.reason.message
                    break
                if time.monotonic() - jog.last_heartbeat_s > timeout_s:
                    reason = "dead-man: heartbeat expired"
                    core.stats.count_deadman_stop()
                    self._stop("service", reason)
                    break
                core.arm.jog(jog.velocity, jog.frame, accel_mm_s2=self._accel())
        except CellError as err:
            reason = f"{err.code}: {err.message}"
        except DriverError as err:
            reason = f"arm error: {err}"
        finally:
            core.arm.settle()
            jog.stopped_reason = reason
            with self._lock:
                if self._jog is jog:
                    self._jog = None
            core.slot.release(jog.motion)
            core.audit.record("service", "jog_end", {}, "stopped", reason)
            core.events.publish("jog", {"jogging": False, "reason": reason})
