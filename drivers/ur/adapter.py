"""Universal Robots e-Series adapter on ur_rtde: :class:`URArm` implements ``drivers.arm.Arm``.

Poses are 4x4 ``T_base_tcp`` in mm here and UR's ``[x, y, z (m), rx, ry, rz (rad)]`` on the
wire. The adapter guards against the ways ur_rtde can hang a caller:

- the ur_rtde clients live in a child process (:mod:`drivers.ur.client_process`) and every
  call has a deadline: a call that overruns, a client that crashes (ur_rtde's own reconnect
  after a dropped connection can) or a controller that vanishes becomes ConnectionLostError,
  and the child is killed rather than trusted again; ``reconnect()`` starts a fresh one;
- before anything is created, plain sockets with timeouts check that the controller answers,
  so an unreachable controller is reported at once;
- moves are sent asynchronously and then watched through the RTDE stream, so a controller
  that dies or freezes mid-move ends in ConnectionLostError within ``stale_after_s``.

The child pushes a state sample whenever the RTDE data changed (at most every
``PUSH_PERIOD_S``, and once after every call, before its reply); reads take the newest pushed
sample and cost no round trip, and each new one goes into a :class:`PoseHistory` (host
``time.monotonic()``). A monitor thread, idle most of the time, notices a stalled or closed
stream and stops a jog whose commands stop arriving.
"""

from __future__ import annotations

import logging
import math
import socket
import struct
import threading
import time
from typing import Any

import numpy as np
from numpy.typing import NDArray

from drivers.arm import ArmState, JogFrame, speedl_accel
from drivers.errors import (
    ConnectionLostError,
    ControllerWatchdogError,
    DriverError,
    EmergencyStopError,
    MotionError,
    NotReadyError,
    ProtectiveStopError,
    UnlockTooEarlyError,
)
from drivers.pose_history import ControllerClock, PoseHistory
from drivers.ur.client_process import (
    CONTROLLER_WATCHDOG_HZ,
    PARENT_LEASE_S,
    Call,
    ClientDied,
    ClientName,
    ClientProcess,
    Create,
    Guard,
    LastScriptEnd,
    RemoteError,
    Request,
    Sample,
    ScriptEnd,
    StateSample,
    Subscribe,
)
from drivers.ur.modes import (
    ESTOP_BITS,
    RobotMode,
    RuntimeState,
    SafetyBits,
    robot_mode_name,
    safety_mode_name,
)
from estimator.transforms import T_from_ur_pose, pose_distance, ur_pose_from_T

log = logging.getLogger(__name__)


RTDE_PORT = 30004
# How long a refused streamed command waits for the RTDE stream to show the control script
# ended (measured: 50 ms missed it on a 2-core host at load 5-12, the stream lagging the client).
SCRIPT_END_SEEN_WITHIN_S = 0.3
DASHBOARD_PORT = 29999
MOVING_QD_RAD_S = 5e-3  # below this the arm counts as standing (controllers report jitter)
UNLOCK_DELAY_S = 5.0  # a UR refuses to unlock a protective stop for this long after it
PUSH_PERIOD_S = 0.008  # pushed samples at most at 125 Hz: plenty for the pose history
PUSH_FRESH_S = 0.25  # a pushed sample older than this is not trusted: ask the child instead
# pose_at: how long a frame's pose waits for a sample newer than its exposure, and how long
# past the exposure it waits for a push before asking the child (two RTDE packages at 125 Hz)
HISTORY_WAIT_S = 0.5
ASK_AFTER_S = 0.02
MONITOR_PERIOD_S = 0.02  # jog-watchdog checks while a jog or a servo twist runs
IDLE_MONITOR_PERIOD_S = 0.25  # otherwise only the stale-stream check (woken when it is due)


def dashboard_stop(host: str, timeout_s: float) -> str:
    """Send the dashboard's ``stop`` (stop the running program, so any motion) on a plain
    socket and return the controller's reply.

    Used before anything else when a link comes back: a controller that was frozen or cut
    off may still be running the move it had, and a fresh ur_rtde client takes a second to
    start, which is a second of motion nobody is watching. ConnectionLostError when the
    dashboard does not answer in time.
    """
    try:
        with socket.create_connection((host, DASHBOARD_PORT), timeout=timeout_s) as sock:
            reader = sock.makefile("rb")
            reader.readline()  # "Connected: Universal Robots Dashboard Server"
            sock.sendall(b"stop\n")
            return reader.readline().decode("utf-8", "replace").strip()
    except OSError as exc:
        raise ConnectionLostError(f"UR controller at {host} is unreachable (dashboard: "
                                  f"{exc})") from exc


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
        watchdog_s: float = 0.25, stale_after_s: float = 1.5, history_samples: int = 5000,
        poll_period_s: float = 0.004,
    ) -> None:
        self.host = host
        self.connect_timeout_s = connect_timeout_s
        self.call_timeout_s = call_timeout_s
        self.watchdog_s = watchdog_s
        self.stale_after_s = stale_after_s
        self.poll_period_s = poll_period_s
        self.history = PoseHistory(history_samples)
        self._clock = ControllerClock()  # the history is stamped on the controller's clock
        self._client: ClientProcess | None = None
        self._last_command: tuple[str, tuple[Any, ...]] = ("", ())
        self._has_control = False
        self._lost_reason: str | None = "not connected"
        self._pstop_latched = False
        self._pstop_seen_s: float | None = None  # when this adapter first saw the stop
        self._tcp_pose: list[float] | None = None  # the TCP set with set_tcp (UR pose)
        self._jog_deadline_s: float | None = None
        self._move_timeout_s = 30.0  # the deadline of the last move sent (see wait_for_motion)
        self._jog_decel_m_s2 = 1.0
        self._last_ts = -1.0
        self._last_ts_change_s = 0.0
        self._stop_monitor = threading.Event()
        self._kick_monitor = threading.Event()  # a jog started: watch its deadline from now
        self._monitor: threading.Thread | None = None
        self._samples = threading.Condition()  # guards the newest sample
        self._latest: StateSample | None = None
        self._latest_rx_s = 0.0
        self._latest_host_s = 0.0  # host time the newest RTDE package was taken (mapped)
        self._subscribed = False

    # -- the client process ------------------------------------------------------------------
    def _request(self, req: Request, timeout_s: float | None = None) -> Any:
        """One request to the ur_rtde clients; a dead or hung client is a lost link."""
        client = self._client
        if client is None:
            raise ConnectionLostError(f"UR controller at {self.host}: not connected")
        try:
            return client.request(req, timeout_s or self.call_timeout_s)
        except ClientDied as exc:
            self._mark_lost(str(exc))
            raise ConnectionLostError(f"UR controller at {self.host}: {exc}") from exc

    def _call(self, client: ClientName, method: str, *args: Any) -> Any:
        return self._request(Call(client, method, args))

    def _ctrl(self, method: str, *args: Any) -> Any:
        self._last_command = (method, args)  # what a refusal names (_raise_command_failure)
        self._check_link()
        if not self._has_control:
            raise NotReadyError(f"{self.host} is not powered on: call power_on() first")
        try:
            return self._call("ctrl", method, *args)
        except RemoteError as exc:
            if exc.kind == "ValueError":  # the client's own range checks
                raise MotionError(f"{method} rejected: {exc}") from exc
            self._mark_lost(f"{method}: {exc}")
            raise ConnectionLostError(f"{method} on {self.host}: {exc}") from exc

    def _dash(self, method: str, *args: Any) -> Any:
        try:
            return self._call("dash", method, *args)
        except RemoteError as exc:
            self._mark_lost(f"dashboard {method}: {exc}")
            raise ConnectionLostError(f"dashboard {method} on {self.host}: {exc}") from exc

    def _sample(self) -> StateSample:
        return self._timed_sample()[0]

    def _timed_sample(self) -> tuple[StateSample, float]:
        """The newest state: the last pushed sample, or (not subscribed yet, or pushes
        lagging) one asked for; with the host time its RTDE package was taken."""
        self._check_link()
        with self._samples:
            sample, rx_s, host_s = self._latest, self._latest_rx_s, self._latest_host_s
        if sample is None or not self._subscribed or time.monotonic() - rx_s > PUSH_FRESH_S:
            sample = self._ask_sample()
            with self._samples:  # the newest kept (a concurrent reply may have overtaken)
                if self._latest is not None:
                    sample, host_s = self._latest, self._latest_host_s
                else:  # nothing kept (a replaced child's reply): when the child saw it
                    now = time.monotonic()
                    host_s = sample.seen_s if 0.0 < sample.seen_s <= now else now
        if not sample.connected:
            self._mark_lost("the RTDE stream was closed by the controller")
            self._check_link()
        return sample, host_s

    def _ask_sample(self) -> StateSample:
        """Ask the child for its newest state (not waiting for a push) and keep it."""
        client = self._client
        try:
            sample = self._request(Sample())
        except RemoteError as exc:
            self._mark_lost(f"state: {exc}")
            raise ConnectionLostError(f"state of {self.host}: {exc}") from exc
        assert sample is not None
        self._accept(sample, client)
        return sample

    # -- connection ----------------------------------------------------------------------------
    def connect(self) -> None:
        """Connect; ConnectionLostError when unreachable, NotReadyError when not in remote.

        The first thing said to a controller is the dashboard's ``stop``: whatever it was
        doing while nobody watched (a move it kept running through a frozen or broken link)
        ends before a new client is even started.
        """
        if self._lost_reason is None:
            return
        reply = dashboard_stop(self.host, self.connect_timeout_s)
        log.info("%s: dashboard stop before connecting: %s", self.host, reply)
        probe_rtde(self.host, self.connect_timeout_s)
        if self._client is not None:
            self._client.kill("replaced")
        client = self._client = ClientProcess(self.host)
        with self._samples:
            self._latest, self._subscribed = None, False
        client.on_push = lambda s: self._accept(s, client)
        # Readers in other threads see "connecting" (not connected) until the receive client
        # exists; only then is the link up.
        self._lost_reason = "connecting"
        try:
            self._request(Create("dash"), timeout_s=self.connect_timeout_s + 5.0)
            self._dash("connect", int(self.connect_timeout_s * 1000))
            if not self._dash("isInRemoteControl"):
                raise NotReadyError(f"UR controller at {self.host} is not in remote control: "
                                    "switch the pendant to Remote")
            self._request(Create("recv"), timeout_s=self.connect_timeout_s + 5.0)
            self._request(Subscribe(PUSH_PERIOD_S))
            self._subscribed = True
        except RemoteError as exc:
            self._lost_reason = f"connect failed: {exc}"
            raise ConnectionLostError(f"cannot connect to {self.host}: {exc}") from exc
        except DriverError as exc:
            self._lost_reason = f"connect failed: {exc}"
            raise
        self._lost_reason = None
        self._last_ts = -1.0
        self._clock = ControllerClock()  # maybe another controller (or clock) now
        self._last_ts_change_s = time.monotonic()
        self._start_monitor()
        sample = self._sample()
        if sample.robot_mode == RobotMode.RUNNING and sample.safety_bits & SafetyBits.NORMAL:
            self._start_control()

    def _start_control(self) -> None:
        """Create the control interface (it uploads ur_rtde's control script)."""
        if self._has_control:
            self._ensure_program()
            return
        deadline = time.monotonic() + self.connect_timeout_s
        while True:
            try:
                self._request(Create("ctrl"), timeout_s=self.connect_timeout_s + 10.0)
                self._request(Guard(CONTROLLER_WATCHDOG_HZ, PARENT_LEASE_S))
                self._has_control = True
                break
            except RemoteError as exc:
                # IN_USE: another client owns the control registers; a real controller
                # refuses the second control connection.
                if "in use" not in str(exc).lower() or time.monotonic() > deadline:
                    raise NotReadyError(f"cannot take control of {self.host}: {exc}") from exc
                time.sleep(0.2)
        if self._tcp_pose is not None:  # a new control script starts with the default TCP
            self._ctrl("setTcp", self._tcp_pose)

    @property
    def connected(self) -> bool:
        return self._lost_reason is None

    def disconnect(self) -> None:
        self._stop_monitor.set()
        self._kick_monitor.set()
        if self._monitor is not None and self._monitor is not threading.current_thread():
            self._monitor.join(timeout=1.0)
        self._monitor = None
        client, healthy = self._client, self._lost_reason is None
        self._client = None
        self._has_control = False
        self._jog_deadline_s = None
        self._lost_reason = "disconnected"
        if client is None:
            return
        if healthy:
            goodbyes: tuple[tuple[ClientName, str], ...] = (
                ("ctrl", "stopScript"), ("ctrl", "disconnect"), ("recv", "disconnect"),
                ("dash", "disconnect"))
            for name, method in goodbyes:
                try:
                    client.request(Call(name, method), self.call_timeout_s)
                except ClientDied:
                    break
                except RemoteError:
                    continue  # e.g. no control client: nothing to close there
            client.close()
        else:
            client.kill("connection lost")

    def reconnect(self) -> None:
        """Drop whatever is left of the old link and connect again."""
        if self._lost_reason is None:
            self._mark_lost("reconnecting")
        self.disconnect()
        self.connect()

    def _start_monitor(self) -> None:
        self._stop_monitor, self._kick_monitor = threading.Event(), threading.Event()
        self._monitor = threading.Thread(
            target=self._monitor_loop, args=(self._stop_monitor, self._kick_monitor),
            daemon=True, name=f"ur-monitor-{self.host}")
        self._monitor.start()

    def _accept(self, sample: StateSample, client: ClientProcess | None) -> None:
        """Keep ``sample`` when it is newer than the one kept (and from the current child);
        new RTDE data also goes into the pose history."""
        if client is not self._client:
            return  # a replaced child's last words
        now = time.monotonic()
        with self._samples:
            latest = self._latest
            if latest is not None and sample.seq <= latest.seq:
                return
            self._latest, self._latest_rx_s = sample, now
            self._note_protective_stop(sample, now)
            if sample.timestamp_s != self._last_ts:
                # when the child first saw it: staleness counts from the data, not the pipe
                seen_s = sample.seen_s if 0.0 < sample.seen_s <= now else now
                self._last_ts, self._last_ts_change_s = sample.timestamp_s, seen_s
                self._latest_host_s = self._clock.host_time(sample.timestamp_s, seen_s)
                self.history.add(self._latest_host_s, T_from_ur_pose(list(sample.tcp_pose)))
            self._samples.notify_all()

    def _monitor_loop(self, stop: threading.Event, kick: threading.Event) -> None:
        """Stale-stream detection and the jog watchdog (the pose history fills from the
        pushed samples, see ``_accept``). Between jogs it sleeps until the stream would turn
        stale (at most ``IDLE_MONITOR_PERIOD_S``); a jog's first command kicks it awake."""
        while True:
            kick.wait(self._monitor_wait_s())
            kick.clear()
            if stop.is_set():
                break
            if self._lost_reason is not None:
                continue
            try:
                self._sample()  # asks the child itself when the pushes lag
            except DriverError:
                continue
            now = time.monotonic()
            if now - self._last_ts_change_s > self.stale_after_s:
                # which side stood still: the controller's data as the ur_rtde child saw
                # it, or the pipe from the child (a stalled child or a starved reader here)
                self._mark_lost(f"no RTDE data for {now - self._last_ts_change_s:.2f} s "
                                f"(the last sample from the ur_rtde child came "
                                f"{now - self._latest_rx_s:.2f} s ago)")
                continue
            if self._jog_deadline_s is not None and now > self._jog_deadline_s:
                try:
                    self._end_jog()
                except DriverError as exc:
                    log.warning("%s: jog watchdog could not stop the arm: %s", self.host, exc)

    def _monitor_wait_s(self) -> float:
        """Until the next check: a period, or less when the stream would turn stale sooner
        (so a stalled stream is noticed right at ``stale_after_s``) or a jog's or servo
        twist's watchdog runs out sooner (so the arm holds a twist for the watchdog time the
        servo law plans with, not up to a period longer)."""
        if self._lost_reason is not None:  # nothing to watch until the next connect
            return IDLE_MONITOR_PERIOD_S
        now = time.monotonic()
        due_s = self._last_ts_change_s + self.stale_after_s - now
        deadline_s = self._jog_deadline_s
        if deadline_s is None:
            period_s = IDLE_MONITOR_PERIOD_S
        else:
            period_s = min(MONITOR_PERIOD_S, deadline_s - now + 0.0005)
        return max(0.001, min(period_s, due_s + 0.0005))

    def _note_protective_stop(self, s: StateSample, now: float) -> None:
        if s.safety_bits & SafetyBits.PROTECTIVE_STOPPED:
            if self._pstop_seen_s is None:
                self._pstop_seen_s = now
        else:
            self._pstop_seen_s = None

    def _mark_lost(self, reason: str) -> None:
        if self._lost_reason is None:
            log.warning("%s: connection lost: %s", self.host, reason)
            self._lost_reason = reason
            self._jog_deadline_s = None
            self._has_control = False
            client = self._client
            if client is not None:
                # a client that lost its controller is not reused: ur_rtde's own reconnect
                # from inside its receive thread is unsafe
                threading.Thread(target=client.kill, args=(reason,), daemon=True).start()

    def _check_link(self) -> None:
        if self._lost_reason is not None:
            raise ConnectionLostError(f"UR controller at {self.host}: {self._lost_reason}")

    # -- power and state -----------------------------------------------------------------------
    def power_on(self) -> None:
        """Power on and release the brakes; returns when the arm is RUNNING (and controlled)."""
        self._raise_if_estopped(self._sample())
        self._dash("powerOn")
        self._dash("brakeRelease")
        deadline = time.monotonic() + 15.0
        while True:
            sample = self._sample()
            self._raise_if_estopped(sample)
            if sample.robot_mode == RobotMode.RUNNING:
                break
            if time.monotonic() > deadline:
                raise NotReadyError(f"{self.host} did not reach RUNNING after power on")
            time.sleep(0.02)
        self._start_control()

    def power_off(self) -> None:
        if self._moving(self._sample()):
            raise NotReadyError(f"{self.host}: power off refused while the arm moves")
        self._dash("powerOff")  # the control script ends with the power; power_on restarts it
        deadline = time.monotonic() + 5.0
        while self._sample().robot_mode not in (RobotMode.POWER_OFF, RobotMode.IDLE):
            if time.monotonic() > deadline:
                raise NotReadyError(f"{self.host} did not power off")
            time.sleep(0.02)

    def state(self) -> ArmState:
        """The newest RTDE state; its ``timestamp_s`` is when the controller took it (host
        clock), so a consumer knows how old the pose is (a servo loop extrapolates it)."""
        try:
            s, taken_s = self._timed_sample()
        except ConnectionLostError:
            span = self.history.span()
            T_last = self.history.at(span[1]) if span else np.eye(4)
            return ArmState(False, "DISCONNECTED", "UNKNOWN", False, T_last, np.zeros(6),
                            time.monotonic())
        return ArmState(
            connected=True,
            robot_mode=robot_mode_name(s.robot_mode),
            safety_status=safety_mode_name(s.safety_mode),
            moving=self._moving(s),
            T_base_tcp=T_from_ur_pose(list(s.tcp_pose)),
            joints_rad=np.asarray(s.q_rad, dtype=float),
            timestamp_s=taken_s,
        )

    def tcp_pose(self) -> NDArray[np.float64]:
        return T_from_ur_pose(list(self._sample().tcp_pose))

    def joint_positions_rad(self) -> NDArray[np.float64]:
        return np.asarray(self._sample().q_rad, dtype=float)

    def forward_kinematics(self, joints_rad: NDArray[np.float64]) -> NDArray[np.float64]:
        """The controller's own forward kinematics (URScript get_forward_kin) with our TCP."""
        q = np.asarray(joints_rad, dtype=float).reshape(-1)
        if q.shape != (6,) or not np.all(np.isfinite(q)):
            raise MotionError(f"joints must be 6 finite values, got {joints_rad!r}")
        if self._has_control:  # the script may have stopped (its watchdog, a stop, an error)
            self._ensure_program()
        pose = self._ctrl("getForwardKinematics", q.tolist(), self._tcp_pose or [0.0] * 6)
        return T_from_ur_pose(list(pose))

    def pose_at(self, timestamp_s: float) -> NDArray[np.float64]:
        """The pose at a frame's exposure, from the samples around it.

        A moving arm's samples are pushed at the RTDE rate, so one newer than the exposure
        comes within a package period or two. A still arm's are held back by the child (up to
        ``QUIET_PUSH_S``) and a frame would wait for them; after ``ASK_AFTER_S`` the adapter
        asks the child instead, which answers with its newest sample, the held one first, so
        the pose is still read from samples on both sides of the exposure."""
        now = time.monotonic()
        if self._lost_reason is not None:
            return self.history.at(timestamp_s)
        deadline_s = min(now, timestamp_s) + HISTORY_WAIT_S
        ask_s = timestamp_s + ASK_AFTER_S
        while not self.history.covers(timestamp_s, min(ask_s, deadline_s) - now):
            now = time.monotonic()
            if now >= deadline_s:
                break
            if now >= ask_s:
                try:
                    self._ask_sample()
                except DriverError:
                    break  # the link is gone: the history answers with what it has
                ask_s = now + ASK_AFTER_S
        return self.history.at(timestamp_s)

    def is_moving(self) -> bool:
        return self._moving(self._sample())

    def _moving(self, s: StateSample) -> bool:
        """Moving as a person means it: joints turning, or a move or jog under way. A
        safety-stopped arm has no move under way, whatever its last command was."""
        turning = bool(np.max(np.abs(s.qd_rad_s)) > MOVING_QD_RAD_S)
        if s.safety_bits & (SafetyBits.PROTECTIVE_STOPPED | ESTOP_BITS):
            return turning
        # a script that ended (its RTDE watchdog, a runtime error) leaves its async progress
        # register as it was: no move is under way then, whatever it says
        under_way = s.async_running and s.runtime_state == RuntimeState.PLAYING
        return turning or self._jog_deadline_s is not None or under_way

    def async_progress(self) -> int:
        """Index of the path segment under way, or -1 when no async move runs."""
        s = self._sample()
        return s.async_progress if s.async_running else -1

    def _raise_if_estopped(self, s: StateSample) -> None:
        if s.safety_bits & ESTOP_BITS:
            raise EmergencyStopError(f"{self.host} is emergency-stopped: release the e-stop, "
                                     "then power on again")

    def _raise_if_stopped(self, s: StateSample) -> None:
        """Typed error for a safety stop; a protective stop latches until recovered."""
        self._raise_if_estopped(s)
        if s.safety_bits & SafetyBits.PROTECTIVE_STOPPED:
            self._pstop_latched = True
            self._note_protective_stop(s, time.monotonic())
        if self._pstop_latched:
            raise ProtectiveStopError(f"{self.host} is protective-stopped: "
                                      "call recover_protective_stop()")

    def _ensure_program(self) -> None:
        """The control script stops on runtime errors and safety stops; upload it again.

        ur_rtde's reuploadScript returns once the script is sent, and its control client
        refuses every command at once until its own RTDE stream (another connection than the
        receive client's, read by another thread, so later on a loaded host) shows the
        script running: the script counts as started when both views say so."""
        if self._sample().runtime_state == RuntimeState.PLAYING:
            return
        self._ctrl("reuploadScript")
        deadline = time.monotonic() + self.connect_timeout_s
        while not (self._sample().runtime_state == RuntimeState.PLAYING
                   and self._control_sees_script()):
            if time.monotonic() > deadline:
                raise NotReadyError(f"{self.host}: the control script did not start")
            time.sleep(0.01)

    def _control_sees_script(self) -> bool:
        """Does ur_rtde's control client see its control script running (its own view)?"""
        last = self._last_command
        try:
            return bool(self._ctrl("isProgramRunning"))
        finally:
            self._last_command = last

    def _ready_for_motion(self) -> StateSample:
        s = self._sample()
        self._raise_if_stopped(s)
        if s.robot_mode != RobotMode.RUNNING or not self._has_control:
            raise NotReadyError(f"{self.host} is not RUNNING: call power_on() first")
        self._ensure_program()
        return s

    # -- motion --------------------------------------------------------------------------------
    def set_tcp(self, T_flange_tcp: NDArray[np.float64]) -> None:
        pose = ur_pose_from_T(_checked_T(T_flange_tcp))
        self._ready_for_motion()
        if not self._ctrl("setTcp", pose):
            self._raise_command_failure("setTcp")
        self._tcp_pose = [float(v) for v in pose]

    def move_linear(
        self, T_base_tcp: NDArray[np.float64], speed_mm_s: float, accel_mm_s2: float,
        wait: bool = True,
    ) -> None:
        pose = ur_pose_from_T(_checked_T(T_base_tcp))
        v, a = _positive(speed_mm_s, "speed") / 1000.0, _positive(accel_mm_s2, "accel") / 1000.0
        s = self._ready_for_motion()
        self._end_jog()
        distance_m = float(np.linalg.norm(np.subtract(pose[:3], s.tcp_pose[:3])))
        turn_rad = pose_distance(T_from_ur_pose(list(s.tcp_pose)), T_base_tcp)[1] * math.pi / 180
        # A UR applies the tool speed to the rotation too (v in rad/s), so a move that
        # mostly turns takes angle / v: the deadline is a watchdog, not the expected time.
        self._move_timeout_s = 2.0 * (max(distance_m, turn_rad) / v + v / a) + 5.0
        if not self._ctrl("moveL", pose, v, a, True):
            self._raise_command_failure("moveL")
        if wait:
            self.wait_for_motion()

    def move_joint(
        self, joints_rad: NDArray[np.float64], speed_rad_s: float, accel_rad_s2: float,
        wait: bool = True,
    ) -> None:
        q = np.asarray(joints_rad, dtype=float).reshape(-1)
        if q.shape != (6,) or not np.all(np.isfinite(q)):
            raise MotionError(f"joints must be 6 finite values, got {joints_rad!r}")
        v, a = _positive(speed_rad_s, "speed"), _positive(accel_rad_s2, "accel")
        s = self._ready_for_motion()
        self._end_jog()
        travel = float(np.max(np.abs(q - np.asarray(s.q_rad))))
        self._move_timeout_s = 2.0 * (travel / v + v / a) + 5.0
        if not self._ctrl("moveJ", q.tolist(), v, a, True):
            self._raise_command_failure("moveJ")
        if wait:
            self.wait_for_motion()

    def _script_ended(self, within_s: float = SCRIPT_END_SEEN_WITHIN_S) -> bool:
        """After a refused command: did the control script end without a safety stop (the
        controller's RTDE watchdog after a host hiccup longer than its period, or a runtime
        error)? Then it is uploaded again (True) and the caller may send its command once
        more: the host that missed the kick is back and streams again. A safety stop raises.

        ur_rtde refuses the command as soon as its client knows the script is gone, while
        the RTDE stream this reads can lag the client by several cycles on a loaded host, so
        the wait is long enough for that; the arm is already braking meanwhile (the ended
        script stopped it), so waiting costs only the retry's delay."""
        deadline = time.monotonic() + within_s
        while True:
            s = self._sample()
            self._raise_if_stopped(s)
            if s.runtime_state != RuntimeState.PLAYING:
                self._ensure_program()
                return True
            if time.monotonic() > deadline:
                return False
            time.sleep(0.005)

    def _raise_command_failure(self, what: str) -> None:
        """The client said False: find out why from the controller's state and from what the
        ur_rtde child saw when the script ended, and raise the typed error. Only what was
        observed is said: a safety stop (typed), the RTDE watchdog that ended the script
        (typed), the script ended on this very command, the script not running (its state),
        or the command refused while the script ran."""
        deadline = time.monotonic() + 0.2  # the stream may lag the client by a cycle or two
        while True:
            s = self._sample()
            self._raise_if_stopped(s)
            if time.monotonic() > deadline:
                break
            time.sleep(0.01)
        command = self._command_words(what)
        if s.runtime_state == RuntimeState.PLAYING:
            raise MotionError(f"{command} was rejected by the controller while its control "
                              "script ran: it did not take this command (check the target "
                              "against the arm's reach and the safety limits)")
        state = (f"runtime state {_runtime_name(s.runtime_state)}, robot mode "
                 f"{robot_mode_name(s.robot_mode)}, safety {safety_mode_name(s.safety_mode)}")
        end = self._last_script_end()
        if end is not None and end.cause == "watchdog":
            raise ControllerWatchdogError(_watchdog_words(self.host, command, end, state))
        if end is not None and end.cause == "command":
            raise MotionError(
                f"{command} was rejected: it ended the controller's control script: it ran "
                "when the command "
                f"was sent and stopped on it ({state}); the controller's log names the "
                "runtime error (a target it cannot reach or that its limits forbid, for one)")
        ended = "" if end is None else (
            f"; it was seen ended {max(0.0, time.monotonic() - end.at_s):.1f} s ago with "
            + ("its RTDE watchdog not armed" if end.allowed_s <= 0 else
               f"its RTDE watchdog kicked in time (kicks stopped at most "
               f"{end.silent_s * 1000:.0f} ms of the {end.allowed_s * 1000:.0f} ms allowed)"))
        raise MotionError(f"{command} was rejected: the controller's control script is not "
                          f"running ({state}){ended}")

    def _command_words(self, what: str) -> str:
        """``what`` with the target it was sent with, when the last command was it."""
        method, args = self._last_command
        if method != what or not args:
            return what
        first = args[0]
        if isinstance(first, list | tuple) and all(isinstance(v, float | int) for v in first):
            return f"{what} to [{', '.join(f'{float(v):.4g}' for v in first)}]"
        return what

    def _last_script_end(self) -> ScriptEnd | None:
        """What the ur_rtde child saw when the control script last ended (None: it saw none,
        or cannot say)."""
        try:
            end = self._request(LastScriptEnd())
        except DriverError:
            return None
        return end if isinstance(end, ScriptEnd) else None

    def wait_for_motion(self, timeout_s: float | None = None) -> None:
        """Until the controller says the move is over: ur_rtde's async operation ended (the
        control script's own progress), never a guess from the pose standing still. Without
        ``timeout_s`` the deadline is the last move's own (twice its planned time, plus 5 s)."""
        if timeout_s is None:
            timeout_s = self._move_timeout_s
        deadline = time.monotonic() + timeout_s
        while True:
            s = self._sample()
            self._raise_if_stopped(s)
            if s.runtime_state != RuntimeState.PLAYING:
                raise MotionError(f"{self.host}: the control program stopped during the move")
            if not s.async_running:
                return
            if time.monotonic() > deadline:
                self.stop()
                raise MotionError(f"{self.host}: move did not finish within {timeout_s:.1f} s")
            time.sleep(self.poll_period_s)

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
        s = self._ready_for_motion()
        v_m, w = twist[:3] / 1000.0, twist[3:]
        if frame == "tool":
            R_base_tcp = T_from_ur_pose(list(s.tcp_pose))[:3, :3]
            v_m, w = R_base_tcp @ v_m, R_base_tcp @ w
        xd = [*map(float, v_m), *map(float, w)]
        if not self._ctrl("speedL", xd, a, 0.0):
            self._raise_command_failure("jog")
        self._jog_decel_m_s2 = max(a, 0.5)
        self._arm_watchdog(self.watchdog_s)

    def servo_twist(
        self, velocity: NDArray[np.float64], accel_mm_s2: float, watchdog_s: float,
        angular_accel_rad_s2: float | None = None,
    ) -> None:
        """Streamed base-frame twist through ur_rtde's speedL (measured against servoL on the
        simulated controller, see cell/bench/approach.py): velocity commands need no pose
        interpolation on the controller, so a late tick only keeps the last velocity instead
        of stalling the arm. The monitor's watchdog brakes when ticks stop.

        ur_rtde's speedL sends one acceleration, which URScript's speedl also takes as the
        rotational one (aRot defaults to a): the larger of the two goes, so both parts reach
        their commanded speed at least as fast as asked (the caller's per-tick ramp sets the
        real acceleration), and the watchdog brakes both at least that hard."""
        twist = np.asarray(velocity, dtype=float).reshape(-1)
        if twist.shape != (6,) or not np.all(np.isfinite(twist)):
            raise MotionError(f"servo twist must be 6 finite values, got {velocity!r}")
        a = speedl_accel(_positive(accel_mm_s2, "accel"), angular_accel_rad_s2)
        watchdog = _positive(watchdog_s, "watchdog")
        self._ready_for_motion()
        xd = [*map(float, twist[:3] / 1000.0), *map(float, twist[3:])]
        if not self._ctrl("speedL", xd, a, 0.0) and not (
                self._script_ended() and self._ctrl("speedL", xd, a, 0.0)):
            self._raise_command_failure("speedL")
        self._jog_decel_m_s2 = max(a, 0.5)
        self._arm_watchdog(watchdog)

    def _arm_watchdog(self, watchdog_s: float) -> None:
        """The twist just sent runs until ``watchdog_s`` from now unless renewed; the monitor
        is woken when it was not watching a deadline already."""
        idle = self._jog_deadline_s is None
        self._jog_deadline_s = time.monotonic() + watchdog_s
        if idle:
            self._kick_monitor.set()

    def _end_jog(self) -> None:
        if self._jog_deadline_s is None:
            return
        self._jog_deadline_s = None
        self._ctrl("speedStop", self._jog_decel_m_s2)

    def stop(self, decel_mm_s2: float = 2000.0) -> None:
        """Stop any motion now. Accepted in any state; ConnectionLostError without a link
        (the next connect stops the controller before anything else)."""
        decel = _positive(decel_mm_s2, "deceleration") / 1000.0
        self._check_link()
        if not self._has_control:
            return  # no control program: nothing of ours is moving
        s = self._sample()
        if s.robot_mode != RobotMode.RUNNING or s.runtime_state != RuntimeState.PLAYING:
            self._jog_deadline_s = None
            return  # powered off, or the control script is not running: nothing moves
        self._jog_deadline_s = None
        self._ctrl("speedStop", decel)
        self._ctrl("stopL", decel, False)

    def recover_protective_stop(self) -> None:
        """Unlock a protective stop (refused by the controller for 5 s after the stop:
        UnlockTooEarlyError with the seconds left), then restart the control program."""
        s = self._sample()
        self._raise_if_estopped(s)
        if s.safety_bits & SafetyBits.PROTECTIVE_STOPPED:
            self._note_protective_stop(s, time.monotonic())
            try:
                self._call("dash", "unlockProtectiveStop")
            except RemoteError as exc:
                if "unlock protective stop failure" not in str(exc).lower():
                    self._mark_lost(f"unlock protective stop: {exc}")
                    raise ConnectionLostError(f"unlock protective stop: {exc}") from exc
                seen = self._pstop_seen_s or time.monotonic()
                left = max(0.1, UNLOCK_DELAY_S - (time.monotonic() - seen))
                raise UnlockTooEarlyError(f"{self.host} refused to unlock: {exc}", left) from exc
            self._dash("closeSafetyPopup")
            deadline = time.monotonic() + 2.0
            while self._sample().safety_bits & SafetyBits.PROTECTIVE_STOPPED:
                if time.monotonic() > deadline:
                    raise NotReadyError(f"{self.host}: protective stop did not clear")
                time.sleep(0.01)
        self._pstop_latched = False
        self._pstop_seen_s = None
        self._start_control()


def _runtime_name(code: int) -> str:
    try:
        return RuntimeState(code).name
    except ValueError:
        return f"UNKNOWN({code})"


def _watchdog_words(host: str, command: str, end: ScriptEnd, state: str) -> str:
    """The message of a control script the controller's RTDE watchdog ended."""
    why = (f"this host's kicks stopped for {end.silent_s * 1000:.0f} ms, more than the "
           f"{end.allowed_s * 1000:.0f} ms its RTDE watchdog allows ({1.0 / end.allowed_s:g} Hz)")
    if end.withheld_s > 0.0:
        why += (f"; the kicks were withheld for {end.withheld_s * 1000:.0f} ms because the "
                "service process was not heard from in time while a streamed motion ran")
    return (f"{command} was rejected: the controller's RTDE watchdog ended the control "
            f"script on {host} ({why}); the arm braked ({state}). Look at the host's load: "
            "the service and its ur_rtde child were not scheduled in time (CPU starved by "
            "other processes, swapping, a stalled disk); the watchdog's rate is the "
            "driver's, not a setting ([robot] watchdog_s is the jog watchdog, [servo] watchdog_s "
            "the servo tick watchdog)")


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
