"""Universal Robots e-Series adapter on ur_rtde: :class:`URArm` implements ``drivers.arm.Arm``.

Poses are 4x4 ``T_base_tcp`` in mm here and UR's ``[x, y, z (m), rx, ry, rz (rad)]`` on the
wire. The adapter guards against the ways ur_rtde can hang a caller:

- every blocking client call runs on a worker thread with a deadline; a call that overruns
  marks the link lost (ConnectionLostError) and its client objects are abandoned, never reused;
- ur_rtde's Python constructors hold the GIL while they talk to the controller, so before
  constructing one the adapter checks with plain sockets (with timeouts) that the controller
  answers at all;
- moves are sent asynchronously and then watched through the RTDE stream, so a controller
  that dies or freezes mid-move ends in ConnectionLostError within ``stale_after_s``, not in
  a client call blocked for minutes.

A monitor thread samples the stream into a :class:`PoseHistory` (host ``time.monotonic()``),
notices a stalled or closed stream, and stops a jog whose commands stop arriving.
"""

from __future__ import annotations

import logging
import math
import socket
import struct
import threading
import time
from collections.abc import Callable
from typing import Any, TypeVar

import numpy as np
from numpy.typing import NDArray

from drivers.arm import ArmState, JogFrame
from drivers.errors import (
    ConnectionLostError,
    EmergencyStopError,
    MotionError,
    NotReadyError,
    ProtectiveStopError,
)
from drivers.pose_history import PoseHistory
from estimator.transforms import T_from_ur_pose, ur_pose_from_T

log = logging.getLogger(__name__)

T = TypeVar("T")

RTDE_PORT = 30004
ROBOT_MODES = {-1: "NO_CONTROLLER", 0: "DISCONNECTED", 1: "CONFIRM_SAFETY", 2: "BOOTING",
               3: "POWER_OFF", 4: "POWER_ON", 5: "IDLE", 6: "BACKDRIVE", 7: "RUNNING",
               8: "UPDATING_FIRMWARE"}
SAFETY_MODES = {1: "NORMAL", 2: "REDUCED", 3: "PROTECTIVE_STOP", 4: "RECOVERY",
                5: "SAFEGUARD_STOP", 6: "SYSTEM_EMERGENCY_STOP", 7: "ROBOT_EMERGENCY_STOP",
                8: "VIOLATION", 9: "FAULT", 10: "VALIDATE_JOINT_ID", 11: "UNDEFINED_SAFETY_MODE",
                12: "AUTOMATIC_MODE_SAFEGUARD_STOP", 13: "SYSTEM_THREE_POSITION_ENABLING_STOP"}
RUNNING_MODE = 7
MOVING_QD_RAD_S = 5e-3  # below this the arm counts as standing (controllers report jitter)
RUNTIME_PLAYING = 2
_PSTOP_BIT, _ESTOP_BITS = 1 << 2, (1 << 5) | (1 << 6) | (1 << 7)

# Client objects whose calls overran their deadline. Their destructors talk to the controller
# while holding the GIL, so they must not be collected while the peer may still be hung.
_ABANDONED: list[Any] = []


def _call_with_deadline(fn: Callable[[], T], timeout_s: float, what: str) -> T:
    """Run a blocking client call on a worker thread; ConnectionLostError past the deadline."""
    box: dict[str, Any] = {}

    def run() -> None:
        try:
            box["value"] = fn()
        except BaseException as exc:
            box["error"] = exc

    worker = threading.Thread(target=run, daemon=True, name=f"ur-call-{what}")
    worker.start()
    worker.join(timeout_s)
    if worker.is_alive():
        raise ConnectionLostError(f"{what}: no answer from the controller within {timeout_s:g} s")
    if "error" in box:
        raise box["error"]
    value: T = box["value"]
    return value


def probe_rtde(host: str, timeout_s: float) -> None:
    """Check that an RTDE server answers a protocol-version request, with timeouts.

    ConnectionLostError when nothing listens or nothing answers in time.
    """
    try:
        with socket.create_connection((host, RTDE_PORT), timeout=timeout_s) as sock:
            sock.sendall(struct.pack(">HBH", 5, 86, 2))  # REQUEST_PROTOCOL_VERSION, v2
            reply = b""
            while len(reply) < 4:
                chunk = sock.recv(4 - len(reply))
                if not chunk:
                    raise ConnectionLostError(f"{host}: RTDE closed the connection")
                reply += chunk
    except OSError as exc:
        raise ConnectionLostError(f"UR controller at {host} is unreachable: {exc}") from exc


class URArm:
    """A UR e-Series arm through ur_rtde (RTDE receive + control, dashboard)."""

    def __init__(
        self, host: str, *, connect_timeout_s: float = 5.0, call_timeout_s: float = 3.0,
        watchdog_s: float = 0.25, stale_after_s: float = 0.75, history_samples: int = 5000,
        poll_period_s: float = 0.004,
    ) -> None:
        self.host = host
        self.connect_timeout_s = connect_timeout_s
        self.call_timeout_s = call_timeout_s
        self.watchdog_s = watchdog_s
        self.stale_after_s = stale_after_s
        self.poll_period_s = poll_period_s
        self.history = PoseHistory(history_samples)
        self._dash: Any = None
        self._recv: Any = None
        self._ctrl: Any = None
        self._ctrl_lock = threading.Lock()
        self._lost_reason: str | None = "not connected"
        self._pstop_latched = False
        self._jog_deadline_s: float | None = None
        self._jog_decel_m_s2 = 1.0
        self._last_ts = -1.0
        self._last_ts_change_s = 0.0
        self._stop_monitor = threading.Event()
        self._monitor: threading.Thread | None = None

    # -- connection ----------------------------------------------------------------------------
    def connect(self) -> None:
        """Connect; ConnectionLostError when unreachable, NotReadyError when not in remote."""
        if self._lost_reason is None:
            return
        import dashboard_client
        import rtde_receive

        probe_rtde(self.host, self.connect_timeout_s)
        dash = dashboard_client.DashboardClient(self.host)
        self._guard(lambda: dash.connect(int(self.connect_timeout_s * 1000)), "dashboard connect",
                    self.connect_timeout_s)
        self._dash = dash
        if not self._guard(dash.isInRemoteControl, "remote control check"):
            raise NotReadyError(f"UR controller at {self.host} is not in remote control: "
                                "switch the pendant to Remote")
        probe_rtde(self.host, self.connect_timeout_s)
        try:
            self._recv = rtde_receive.RTDEReceiveInterface(self.host)
        except RuntimeError as exc:
            raise ConnectionLostError(f"RTDE receive on {self.host}: {exc}") from exc
        self._last_ts = -1.0
        self._last_ts_change_s = time.monotonic()
        self._lost_reason = None
        self._start_monitor()
        if self._recv.getRobotMode() == RUNNING_MODE and self._safety_bits() == 1:
            self._start_control()

    def _start_control(self) -> None:
        """Create the control interface (uploads ur_rtde's control script)."""
        import rtde_control

        if self._ctrl is not None:
            self._ensure_program()
            return
        deadline = time.monotonic() + self.connect_timeout_s
        while True:
            probe_rtde(self.host, self.connect_timeout_s)
            try:
                self._ctrl = rtde_control.RTDEControlInterface(self.host)
                return
            except RuntimeError as exc:
                # IN_USE: another client (or our own abandoned one, still closing) owns the
                # control registers; a real controller refuses the second control connection.
                if "in use" not in str(exc).lower() or time.monotonic() > deadline:
                    raise NotReadyError(f"cannot take control of {self.host}: {exc}") from exc
                time.sleep(0.2)

    def disconnect(self) -> None:
        self._stop_monitor.set()
        if self._monitor is not None and self._monitor is not threading.current_thread():
            self._monitor.join(timeout=1.0)
        self._monitor = None
        ctrl, recv, dash = self._ctrl, self._recv, self._dash
        self._ctrl = self._recv = self._dash = None
        healthy = self._lost_reason is None
        self._lost_reason = "disconnected"
        for obj, name in ((ctrl, "control"), (recv, "receive"), (dash, "dashboard")):
            if obj is None:
                continue
            try:
                if healthy and name == "control":
                    _call_with_deadline(obj.stopScript, self.call_timeout_s, "stop script")
                _call_with_deadline(obj.disconnect, self.call_timeout_s, f"{name} disconnect")
            except Exception as exc:  # closing is best effort; a hung object is abandoned
                log.warning("%s: %s disconnect: %s", self.host, name, exc)
                _ABANDONED.append(obj)

    def reconnect(self) -> None:
        """Drop whatever is left of the old link and connect again."""
        if self._lost_reason is None:
            self._lost_reason = "reconnecting"
        self.disconnect()
        self.connect()

    def _start_monitor(self) -> None:
        self._stop_monitor = threading.Event()
        self._monitor = threading.Thread(target=self._monitor_loop, daemon=True,
                                         name=f"ur-monitor-{self.host}")
        self._monitor.start()

    def _monitor_loop(self) -> None:
        """Pose history, stale-stream detection and the jog watchdog."""
        while not self._stop_monitor.wait(self.poll_period_s):
            recv = self._recv
            if recv is None or self._lost_reason is not None:
                continue
            now = time.monotonic()
            if not recv.isConnected():
                self._mark_lost("the RTDE stream was closed by the controller")
                continue
            ts = recv.getTimestamp()
            if ts != self._last_ts:
                self._last_ts, self._last_ts_change_s = ts, now
                self.history.add(now, T_from_ur_pose(recv.getActualTCPPose()))
            elif now - self._last_ts_change_s > self.stale_after_s:
                self._mark_lost(f"no RTDE data for {now - self._last_ts_change_s:.2f} s")
                continue
            if self._jog_deadline_s is not None and now > self._jog_deadline_s:
                try:
                    self._end_jog()
                except Exception as exc:
                    log.warning("%s: jog watchdog could not stop the arm: %s", self.host, exc)

    def _mark_lost(self, reason: str) -> None:
        if self._lost_reason is None:
            log.warning("%s: connection lost: %s", self.host, reason)
            self._lost_reason = reason
            self._jog_deadline_s = None

    def _guard(self, fn: Callable[[], T], what: str, timeout_s: float | None = None) -> T:
        """A blocking client call with a deadline; failures become typed errors."""
        try:
            return _call_with_deadline(fn, timeout_s or self.call_timeout_s, what)
        except ConnectionLostError as exc:
            self._mark_lost(str(exc))
            raise
        except (RuntimeError, OSError) as exc:
            self._mark_lost(f"{what}: {exc}")
            raise ConnectionLostError(f"{what} on {self.host}: {exc}") from exc

    def _control(self, fn: Callable[[Any], T], what: str) -> T:
        """Run one call on the control interface, serialised with the other callers."""
        self._check_link()
        ctrl = self._ctrl
        if ctrl is None:
            raise NotReadyError(f"{self.host} is not powered on: call power_on() first")
        with self._ctrl_lock:
            try:
                return self._guard(lambda: fn(ctrl), what)
            except ConnectionLostError:
                _ABANDONED.append(ctrl)
                self._ctrl = None
                raise

    def _check_link(self) -> None:
        if self._lost_reason is not None:
            raise ConnectionLostError(f"UR controller at {self.host}: {self._lost_reason}")

    # -- power and state -----------------------------------------------------------------------
    def power_on(self) -> None:
        """Power on and release the brakes; returns when the arm is RUNNING (and controlled)."""
        self._check_link()
        self._raise_if_estopped()
        dash = self._dash
        self._guard(dash.powerOn, "power on")
        self._guard(dash.brakeRelease, "brake release")
        deadline = time.monotonic() + 15.0
        while self._recv.getRobotMode() != RUNNING_MODE:
            self._check_link()
            self._raise_if_estopped()
            if time.monotonic() > deadline:
                raise NotReadyError(f"{self.host} did not reach RUNNING after power on")
            time.sleep(0.02)
        self._start_control()

    def state(self) -> ArmState:
        recv = self._recv
        connected = self._lost_reason is None and recv is not None
        if not connected:
            span = self.history.span()
            T_last = self.history.at(span[1]) if span else np.eye(4)
            return ArmState(False, "DISCONNECTED", "UNKNOWN", False, T_last, np.zeros(6),
                            time.monotonic())
        return ArmState(
            connected=True,
            robot_mode=ROBOT_MODES.get(recv.getRobotMode(), "UNKNOWN"),
            safety_status=SAFETY_MODES.get(recv.getSafetyMode(), "UNKNOWN"),
            moving=self.is_moving(),
            T_base_tcp=T_from_ur_pose(recv.getActualTCPPose()),
            joints_rad=np.asarray(recv.getActualQ(), dtype=float),
            timestamp_s=time.monotonic(),
        )

    def tcp_pose(self) -> NDArray[np.float64]:
        self._check_link()
        return T_from_ur_pose(self._recv.getActualTCPPose())

    def joint_positions_rad(self) -> NDArray[np.float64]:
        self._check_link()
        return np.asarray(self._recv.getActualQ(), dtype=float)

    def pose_at(self, timestamp_s: float) -> NDArray[np.float64]:
        return self.history.at(timestamp_s)

    def is_moving(self) -> bool:
        self._check_link()
        if self._jog_deadline_s is not None:
            return True
        ctrl = self._ctrl
        if ctrl is not None and ctrl.getAsyncOperationProgressEx().isAsyncOperationRunning():
            return True
        return bool(np.max(np.abs(self._recv.getActualQd())) > MOVING_QD_RAD_S)

    def _safety_bits(self) -> int:
        return int(self._recv.getSafetyStatusBits())

    def _raise_if_estopped(self) -> None:
        if self._safety_bits() & _ESTOP_BITS:
            raise EmergencyStopError(f"{self.host} is emergency-stopped: release the e-stop, "
                                     "then power on again")

    def _raise_if_stopped(self) -> None:
        """Typed error for a safety stop; a protective stop latches until recovered."""
        self._raise_if_estopped()
        if self._safety_bits() & _PSTOP_BIT:
            self._pstop_latched = True
        if self._pstop_latched:
            raise ProtectiveStopError(f"{self.host} is protective-stopped: "
                                      "call recover_protective_stop()")

    def _ensure_program(self) -> None:
        """The control script stops on runtime errors and safety stops; upload it again."""
        if self._recv.getRuntimeState() == RUNTIME_PLAYING:
            return
        self._control(lambda c: c.reuploadScript(), "re-upload control script")
        deadline = time.monotonic() + self.connect_timeout_s
        while self._recv.getRuntimeState() != RUNTIME_PLAYING:
            self._check_link()
            if time.monotonic() > deadline:
                raise NotReadyError(f"{self.host}: the control script did not start")
            time.sleep(0.01)

    def _ready_for_motion(self) -> None:
        self._check_link()
        self._raise_if_stopped()
        if self._recv.getRobotMode() != RUNNING_MODE or self._ctrl is None:
            raise NotReadyError(f"{self.host} is not RUNNING: call power_on() first")
        self._ensure_program()

    # -- motion --------------------------------------------------------------------------------
    def set_tcp(self, T_flange_tcp: NDArray[np.float64]) -> None:
        pose = ur_pose_from_T(_checked_T(T_flange_tcp))
        self._ready_for_motion()
        if not self._control(lambda c: c.setTcp(pose), "set TCP"):
            self._raise_command_failure("setTcp")

    def move_linear(
        self, T_base_tcp: NDArray[np.float64], speed_mm_s: float, accel_mm_s2: float,
        wait: bool = True,
    ) -> None:
        pose = ur_pose_from_T(_checked_T(T_base_tcp))
        v, a = _positive(speed_mm_s, "speed") / 1000.0, _positive(accel_mm_s2, "accel") / 1000.0
        self._ready_for_motion()
        self._end_jog()
        distance_m = float(np.linalg.norm(np.subtract(pose[:3], ur_pose_from_T(
            self.tcp_pose())[:3])))
        self._start_async(lambda c: c.moveL(pose, v, a, True), "moveL")
        if wait:
            self._wait_for_motion(2.0 * (distance_m / v + v / a) + 5.0)

    def move_joint(
        self, joints_rad: NDArray[np.float64], speed_rad_s: float, accel_rad_s2: float,
        wait: bool = True,
    ) -> None:
        q = np.asarray(joints_rad, dtype=float).reshape(-1)
        if q.shape != (6,) or not np.all(np.isfinite(q)):
            raise MotionError(f"joints must be 6 finite values, got {joints_rad!r}")
        v, a = _positive(speed_rad_s, "speed"), _positive(accel_rad_s2, "accel")
        self._ready_for_motion()
        self._end_jog()
        travel = float(np.max(np.abs(q - self.joint_positions_rad())))
        self._start_async(lambda c: c.moveJ(q.tolist(), v, a, True), "moveJ")
        if wait:
            self._wait_for_motion(2.0 * (travel / v + v / a) + 5.0)

    def _start_async(self, fn: Callable[[Any], bool], what: str) -> None:
        try:
            ok = self._control(fn, what)
        except ValueError as exc:  # the client's own range checks
            raise MotionError(f"{what} rejected: {exc}") from exc
        if not ok:
            self._raise_command_failure(what)

    def _raise_command_failure(self, what: str) -> None:
        """The client said False: find out why from the stream and raise the typed error."""
        deadline = time.monotonic() + 0.2  # the stream may lag the client by a cycle or two
        while True:
            self._check_link()
            self._raise_if_stopped()
            if time.monotonic() > deadline:
                break
            time.sleep(0.01)
        running = self._recv.getRuntimeState() == RUNTIME_PLAYING
        raise MotionError(f"{what} was rejected by the controller"
                          + ("" if running else " (runtime error: the target is unreachable, "
                             "outside the limits or not allowed)"))

    def _wait_for_motion(self, timeout_s: float) -> None:
        deadline = time.monotonic() + timeout_s
        ctrl = self._ctrl
        while True:
            self._check_link()
            self._raise_if_stopped()
            if self._recv.getRuntimeState() != RUNTIME_PLAYING:
                raise MotionError(f"{self.host}: the control program stopped during the move")
            if ctrl is None or not ctrl.getAsyncOperationProgressEx().isAsyncOperationRunning():
                return
            if time.monotonic() > deadline:
                self.stop()
                raise MotionError(f"{self.host}: move did not finish within {timeout_s:.1f} s")
            time.sleep(self.poll_period_s)

    def async_progress(self) -> int:
        """Index of the path segment under way, or -1 when no async move runs."""
        self._check_link()
        ctrl = self._ctrl
        if ctrl is None:
            return -1
        status = ctrl.getAsyncOperationProgressEx()
        return int(status.progress()) if status.isAsyncOperationRunning() else -1

    def jog(
        self, velocity: NDArray[np.float64], frame: JogFrame = "base",
        accel_mm_s2: float = 500.0,
    ) -> None:
        twist = np.asarray(velocity, dtype=float).reshape(-1)
        if twist.shape != (6,) or not np.all(np.isfinite(twist)):
            raise MotionError(f"jog velocity must be 6 finite values, got {velocity!r}")
        if frame not in ("base", "tool"):
            raise MotionError(f"jog frame must be 'base' or 'tool', got {frame!r}")
        a = _positive(accel_mm_s2, "accel") / 1000.0
        v_m, w = twist[:3] / 1000.0, twist[3:]
        if frame == "tool":
            R_base_tcp = self.tcp_pose()[:3, :3]
            v_m, w = R_base_tcp @ v_m, R_base_tcp @ w
        self._ready_for_motion()
        xd = [*map(float, v_m), *map(float, w)]
        if not self._control(lambda c: c.speedL(xd, a, 0.0), "jog (speedL)"):
            self._raise_command_failure("jog")
        self._jog_decel_m_s2 = max(a, 0.5)
        self._jog_deadline_s = time.monotonic() + self.watchdog_s

    def _end_jog(self) -> None:
        if self._jog_deadline_s is None:
            return
        self._jog_deadline_s = None
        decel = self._jog_decel_m_s2
        self._control(lambda c: c.speedStop(decel), "stop jog (speedStop)")

    def stop(self, decel_mm_s2: float = 2000.0) -> None:
        """Stop any motion now. Accepted in any state; ConnectionLostError without a link."""
        decel = _positive(decel_mm_s2, "deceleration") / 1000.0
        self._check_link()
        if self._ctrl is None:
            return  # no control program: nothing of ours is moving
        self._jog_deadline_s = None
        self._control(lambda c: c.speedStop(decel), "speedStop")
        self._control(lambda c: c.stopL(decel, False), "stopL")

    def recover_protective_stop(self) -> None:
        """Unlock a protective stop (refused by the controller for 5 s after the stop:
        NotReadyError), then restart the control program."""
        self._check_link()
        self._raise_if_estopped()
        if self._safety_bits() & _PSTOP_BIT:
            try:
                _call_with_deadline(self._dash.unlockProtectiveStop, self.call_timeout_s,
                                    "unlock protective stop")
            except ConnectionLostError as exc:
                self._mark_lost(str(exc))
                raise
            except RuntimeError as exc:
                if "unlock protective stop failure" not in str(exc).lower():
                    self._mark_lost(f"unlock protective stop: {exc}")
                    raise ConnectionLostError(f"unlock protective stop: {exc}") from exc
                raise NotReadyError(f"{self.host} refused to unlock: {exc}") from exc
            self._guard(self._dash.closeSafetyPopup, "close safety popup")
            deadline = time.monotonic() + 2.0
            while self._safety_bits() & _PSTOP_BIT:
                self._check_link()
                if time.monotonic() > deadline:
                    raise NotReadyError(f"{self.host}: protective stop did not clear")
                time.sleep(0.01)
        self._pstop_latched = False
        if self._ctrl is None:
            self._start_control()
        else:
            self._ensure_program()


def _checked_T(T: NDArray[np.float64]) -> NDArray[np.float64]:
    M = np.asarray(T, dtype=float)
    if M.shape != (4, 4) or not np.all(np.isfinite(M)):
        raise MotionError(f"expected a finite 4x4 transform, got shape {M.shape}")
    R = M[:3, :3]
    if not np.allclose(R.T @ R, np.eye(3), atol=1e-6) or np.linalg.det(R) < 0:
        raise MotionError("the transform's rotation is not a proper rotation matrix")
    return M


def _positive(x: float, what: str) -> float:
    v = float(x)
    if not math.isfinite(v) or v <= 0:
        raise MotionError(f"{what} must be a positive number, got {x!r}")
    return v
