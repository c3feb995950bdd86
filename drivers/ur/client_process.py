"""ur_rtde in a child process, driven over a pipe by :class:`ClientProcess`.

Why a process and not just threads: ur_rtde's Python constructors hold the GIL while they wait
on the controller (a hung controller would freeze the whole program), its client calls can
block for minutes when the peer vanishes, and after a dropped connection its control interface
reconnects from inside its own receive thread and can crash the process. In a child, a hang is
ended with SIGKILL and a crash is a closed pipe: both become ConnectionLostError in the parent.

Frames are length-prefixed pickles of the typed messages below (both ends are this module):
requests are :class:`Create`, :class:`Call`, :class:`Sample`, :class:`Subscribe` and
:class:`Drop`; a sample comes back as a :class:`StateSample`. Requests are served
concurrently, so a long move does not block the state sampling that watches it.

After :class:`Subscribe` the child pushes samples (reply id 0) instead of being polled: its
pusher thread sleeps between looks at the receive client's package timestamp and sends a
sample only when the RTDE data changed (at most the subscribed rate), and after every call it
sends one before the call's reply, so a sample read after a command's reply reflects the
command. A still arm's samples are held back (see :class:`_PushState`); the one held goes out
before the answer to a :class:`Sample` request. Samples carry a sequence number in the order
they were taken.
"""

from __future__ import annotations

import contextlib
import ctypes
import itertools
import logging
import os
import pickle
import select
import signal
import struct
import subprocess
import sys
import threading
import time
from collections.abc import Callable
from concurrent.futures import Future
from concurrent.futures import TimeoutError as FutureTimeout
from dataclasses import dataclass
from typing import IO, Any, Literal

from drivers.ur.timer_slack import set_timer_slack, timer_slack

_LEN = struct.Struct(">I")
PUSH_ID = 0  # the reply id of pushed samples (request ids start at 1)
RECV_FREQUENCY_HZ = 125.0  # the receive client's RTDE rate: enough for the pose history
PUSH_CHECK_S = 0.004  # how often the pusher looks at the package timestamp (two cheap reads)
# ... and while the arm has stood still, with no call made, for RESTING_AFTER_S: a motion the
# cell did not command (the pendant, a protective stop) is seen at most this much later.
RESTING_CHECK_S = 0.032
RESTING_AFTER_S = 0.5
# Timer slack of the clients' own threads (see drivers.ur.timer_slack): a package is read at most
# this much later, for a fifth of the idle CPU. The receive client's packages come every 8 ms,
# the control client's every 2 ms: its slack stays at 1 ms (with 2 ms an idle minute showed no
# lag, but the servo benchmark's tracking fell apart: 30-77 mm RMS, the arm still 1.2 s after
# a lost target).
TIMER_SLACK_S: dict[str, float] = {"recv": 0.002, "ctrl": 0.001, "dash": 0.002}
PUSHER_TIMER_SLACK_S = 0.001
# A standing arm (see _PushState): one sample per QUIET_PUSH_S, well inside the adapter's
# PUSH_FRESH_S; the deadbands are far below what the cell resolves (1e-5 rad is 10 um at 1 m)
QUIET_PUSH_S = 0.1
STILL_DEADBAND_RAD = 1e-5
STILL_DEADBAND_RAD_S = 1e-4
STILL_DEADBAND_M_RAD = 1e-5

# The controller's own watchdog (ur_rtde's setWatchdog): its control script stops the program,
# braking the arm, when no RTDE input arrives for 1 / CONTROLLER_WATCHDOG_HZ. The child kicks it
# every KICK_PERIOD_S, but only while the parent has been heard from within PARENT_LEASE_S (its
# heartbeat comes every HEARTBEAT_S): a frozen child and a frozen parent both stop the arm.
CONTROLLER_WATCHDOG_HZ = 12.5
# While no streamed motion runs (a planned move, which ends at its own checked target, a stop,
# or nothing), the watchdog runs at this lower rate: a host starved for a few hundred ms (a
# loaded machine) does not end the control script under a healthy planned move, and a dead host
# still stops it within a second. The rate switches to CONTROLLER_WATCHDOG_HZ before the first
# streamed command of a stream reaches the controller, and back once the stream has ended.
PLANNED_WATCHDOG_HZ = 1.0
KICK_PERIOD_S = 0.02
PARENT_LEASE_S = 0.06
HEARTBEAT_S = 0.02
# a child that takes no request (a heartbeat) for this long has stopped reading: it is killed
HEARTBEAT_WRITE_S = 3.0
QUIET_AFTER_CALL_S = 0.02
# ur_rtde's control commands that return without the script's answer (streamed ones)
STREAMED_METHODS = frozenset({"speedL", "speedJ", "servoL", "servoJ", "servoC", "forceMode",
                              "jogStart", "kickWatchdog"})
# motion commands that end a stream: a planned move or a stop runs to its own end
ENDS_STREAM = frozenset({"moveL", "moveJ", "movePath", "moveUntilContact", "speedStop",
                         "servoStop", "stopL", "stopJ", "jogStop", "forceModeStop",
                         "reuploadScript", "stopScript"})
# planned moves: the watchdog goes to its low rate before they start (stops are sent first and
# the rate lowered after them, so a stop never waits behind a setWatchdog round trip)
PLANNED_MOVES = frozenset({"moveL", "moveJ", "movePath", "moveUntilContact"})
# commands the control script carries out (False: the script refused or ended), and how long
# the control client's view may take to show a script that ended on one
COMMANDS_SCRIPT_RUNS = (STREAMED_METHODS | ENDS_STREAM | {"setTcp", "setPayload"}) - {
    "reuploadScript", "stopScript", "kickWatchdog"}
SCRIPT_END_SEEN_S = 0.2
SILENCE_MEMORY_S = 1.0  # a stall of the kicker counts this long for a script end seen after it
RUNTIME_PLAYING = 2  # RTDE runtime_state: the control script runs
PR_SET_PDEATHSIG = 1

ClientName = Literal["dash", "recv", "ctrl"]


@dataclass(frozen=True)
class Create:
    """Create one ur_rtde client (its constructor connects, and may block for long)."""

    client: ClientName


@dataclass(frozen=True)
class Call:
    """Call a ur_rtde method by its own name on one client."""

    client: ClientName
    method: str
    args: tuple[Any, ...] = ()


@dataclass(frozen=True)
class Sample:
    """Read everything the adapter watches from the clients' cached state."""


@dataclass(frozen=True)
class Subscribe:
    """Push samples from now on, whenever the RTDE data changed, at most every ``period_s``."""

    period_s: float


@dataclass(frozen=True)
class Drop:
    """Forget a client (after its connection is known to be gone)."""

    client: ClientName


@dataclass(frozen=True)
class Guard:
    """Arm the controller's watchdog at ``min_frequency_hz`` (again after every script upload)
    and kick it while the child runs; while a streamed motion (speedL, servo) runs, only while
    the parent's heartbeats keep coming within ``parent_lease_s``. A planned move or a stop
    ends on its own, so a parent that is late (starved, not frozen) does not end it."""

    min_frequency_hz: float
    parent_lease_s: float
    planned_frequency_hz: float = PLANNED_WATCHDOG_HZ


@dataclass(frozen=True)
class Heartbeat:
    """The parent is alive (handled inline, no reply)."""


@dataclass(frozen=True)
class LastScriptEnd:
    """How the last control script this child saw end ended: a :class:`ScriptEnd` or None."""


Request = Create | Call | Sample | Subscribe | Drop | Guard | LastScriptEnd


@dataclass(frozen=True)
class ScriptEnd:
    """What this child knew when it first saw a control script no longer running.

    ``cause``: ``"watchdog"`` when the controller's RTDE watchdog was armed and this host's
    kicks had stopped for longer than the watchdog allows (``silent_s`` > ``allowed_s``: the
    kicker thread was not scheduled, or the kicks were withheld on purpose because the
    service process was late mid-stream, ``withheld_s``), ``"command"`` when the script ran
    when ``method`` was sent and ended on it, ``"unknown"`` otherwise (ended while the
    watchdog was kicked in time: a stop from the pendant or the dashboard, for one)."""

    cause: Literal["watchdog", "command", "unknown"]
    at_s: float  # time.monotonic() when it was seen (one clock for every process on a host)
    silent_s: float  # the longest time this host's kicks had stopped, just before
    allowed_s: float  # 1 / the watchdog's armed rate (0.0: not armed)
    withheld_s: float = 0.0  # kicks withheld for this long (the service process was late)
    method: str = ""  # the control call that found it ended


@dataclass(frozen=True)
class StateSample:
    """One consistent read of the receive (and control) client's state, UR units."""

    connected: bool
    timestamp_s: float  # controller time of the RTDE package
    tcp_pose: tuple[float, ...]  # [x, y, z (m), rx, ry, rz (rad)]
    q_rad: tuple[float, ...]
    qd_rad_s: tuple[float, ...]
    robot_mode: int
    safety_mode: int
    safety_bits: int
    runtime_state: int
    async_running: bool = False  # ur_rtde's async operation (moveL/moveJ/path) under way
    async_progress: int = -1
    seq: int = 0  # order in which the child took its samples (later = larger)
    seen_s: float = 0.0  # host time.monotonic() when the child first saw this package


def describe(req: Request) -> str:
    """A request in words, for timeouts and logs."""
    if isinstance(req, Call):
        return f"{req.client}.{req.method}"
    if isinstance(req, Sample):
        return "sample"
    if isinstance(req, Subscribe):
        return "subscribe"
    if isinstance(req, Guard):
        return "guard"
    if isinstance(req, LastScriptEnd):
        return "last script end"
    return f"{type(req).__name__.lower()} {req.client}"


class ClientDied(Exception):
    """The child process is gone (crashed, killed) or stopped answering."""


class RemoteError(Exception):
    """An exception raised by ur_rtde in the child: ``kind`` is its Python type name."""

    def __init__(self, kind: str, message: str) -> None:
        super().__init__(message)
        self.kind = kind


def _write(stream: IO[bytes], obj: object, lock: threading.Lock) -> None:
    data = pickle.dumps(obj)
    with lock:
        stream.write(_LEN.pack(len(data)) + data)
        stream.flush()


def _write_within(fd: int, data: bytes, deadline_s: float) -> None:
    """All of ``data`` into the non-blocking ``fd`` by ``deadline_s`` (monotonic); TimeoutError
    when its reader does not take it in time (a child that stopped reading: its pipe is full,
    and a blocking write would hold every later request, a stop's too, for as long)."""
    view = memoryview(data)
    while view:
        try:
            view = view[os.write(fd, view):]
            continue
        except BlockingIOError:
            pass
        remaining_s = deadline_s - time.monotonic()
        if remaining_s <= 0.0:
            raise TimeoutError(f"{len(view)} of {len(data)} bytes not taken")
        select.select([], [fd], [], remaining_s)


def _read(stream: IO[bytes]) -> Any:
    head = stream.read(_LEN.size)
    if len(head) < _LEN.size:
        raise EOFError
    (n,) = _LEN.unpack(head)
    body = stream.read(n)
    if len(body) < n:
        raise EOFError
    return pickle.loads(body)


# -- the child -------------------------------------------------------------------------------

class _Clients:
    """The ur_rtde objects of one controller, living in the child."""

    def __init__(self, host: str) -> None:
        self.host = host
        self.objects: dict[str, Any] = {}
        self.locks = {name: threading.Lock() for name in ("dash", "recv", "ctrl")}
        self._seq = itertools.count(1)
        self._seq_lock = threading.Lock()
        self.push_period_s: float | None = None  # set by Subscribe
        self._seen = (-1.0, 0.0)  # (package timestamp, when it was first seen)
        self.guard: Guard | None = None
        self.parent_seen_s = time.monotonic()  # the parent's last message
        self.watchdog_armed = False  # setWatchdog accepted by the script running now
        self.armed_hz = 0.0  # the rate it was armed at
        # the rate the controller's watchdog last accepted: what guarded the script that ran
        # (a setWatchdog refused because the script has just ended, or the kicker seeing it
        # ended, leaves the watchdog that ended it as it was); a new upload starts without one
        self.guarded_hz = 0.0
        self.ctrl_ended_s = 0.0  # when the last control call returned
        self.last_call_streamed = False  # it was a streamed command (see STREAMED_METHODS)
        self.streaming = False  # a streamed motion was the last motion command (see kick)
        self.call_ended = threading.Event()  # an answered control call just returned
        self.last_tick_s = time.monotonic()  # the kicker's last turn
        self.tick_gap = (0.0, 0.0)  # (the longest recent gap between turns, when it ended)
        self.withheld_since_s: float | None = None  # kicks withheld: the parent is late
        self.script_live = False  # a script was seen running and its end not noted yet
        self._end_lock = threading.Lock()
        self.script_end: ScriptEnd | None = None  # the last end seen (see _note_end)

    def arm_watchdog(self) -> None:
        """setWatchdog on the control script (a new script starts without one). Refused
        while no script runs (ur_rtde answers False): the kicker tries again once one runs."""
        ctrl = self.objects.get("ctrl")
        if ctrl is not None and self.guard is not None:
            with self.locks["ctrl"]:
                self._set_rate(ctrl, self._wanted_hz())

    def _wanted_hz(self) -> float:
        guard = self.guard
        assert guard is not None
        return guard.min_frequency_hz if self.streaming else guard.planned_frequency_hz

    def _set_rate(self, ctrl: Any, hz: float) -> None:
        """setWatchdog at ``hz`` (the caller holds the control lock)."""
        self.watchdog_armed = bool(ctrl.setWatchdog(hz))
        self.armed_hz = hz if self.watchdog_armed else 0.0
        if self.watchdog_armed:
            self.guarded_hz = hz

    def _script_running(self) -> bool:
        recv = self.objects.get("recv")
        return recv is not None and int(recv.getRuntimeState()) == RUNTIME_PLAYING

    def kick(self) -> None:
        """One kick of the controller's watchdog, when armed and the parent is alive.

        A kick writes the script's command register, so it must not land before the script
        has taken a call's command (that command would be lost, and a call waiting for its
        answer would hang): kicks go out only between calls, and not within QUIET_AFTER_CALL_S
        of a streamed one (those return at once, before the script's next cycle). An answered
        call has left the script done with its command, so the kicker kicks right after it
        (it waited for its next tick before, and a call that took a few loaded script cycles
        plus that wait outlasted the watchdog on a healthy host). A blocking call (a
        stop waiting for the arm to rest) is not kicked through: ur_rtde's kick would wait for
        the script to be ready, and its sends are not made for two threads at once."""
        now = time.monotonic()
        gap, self.last_tick_s = now - self.last_tick_s, now
        if gap >= self.tick_gap[0] or now - self.tick_gap[1] > SILENCE_MEMORY_S:
            self.tick_gap = (gap, now)
        ctrl, guard = self.objects.get("ctrl"), self.guard
        if ctrl is None or guard is None:
            return
        if self.streaming and time.monotonic() - self.parent_seen_s > guard.parent_lease_s:
            if self.withheld_since_s is None:
                self.withheld_since_s = time.monotonic()
            if not self._script_running() and not self.locks["ctrl"].locked():
                self._note_end()
            return  # the parent stalled mid-stream: let the controller stop the arm
        if not self._script_running():
            if not self.locks["ctrl"].locked():  # else the call in flight notes it
                self._note_end()
            self.watchdog_armed = False  # the script ended: the next one starts unguarded
            self.streaming = False
            self.withheld_since_s = None
            return
        self.withheld_since_s = None
        with self._end_lock:
            self.script_live = True
        lock = self.locks["ctrl"]
        if not lock.acquire(blocking=False):
            return
        try:
            if (not self.last_call_streamed
                    or time.monotonic() - self.ctrl_ended_s >= QUIET_AFTER_CALL_S):
                with contextlib.suppress(Exception):
                    if self.watchdog_armed:
                        ctrl.kickWatchdog()
                    else:  # a script that started without one (not via reuploadScript)
                        self._set_rate(ctrl, self._wanted_hz())
        finally:
            lock.release()

    def _allowed_s(self) -> float:
        """How long the controller's watchdog lets the live script go without a write (0: not
        armed): the rate it last accepted, whatever was asked of it since the script ended."""
        return 1.0 / self.guarded_hz if self.guarded_hz > 0 else 0.0

    def _silent_s(self) -> float:
        """How long this host's kicks have stopped lately: the kicker not scheduled (the
        longest recent gap between its turns, or the time since its last), or kicks
        withheld while the service process was late."""
        now = time.monotonic()
        recent = self.tick_gap[0] if now - self.tick_gap[1] <= SILENCE_MEMORY_S else 0.0
        withheld = 0.0 if self.withheld_since_s is None else now - self.withheld_since_s
        return max(recent, now - self.last_tick_s, withheld)

    def _note_end(self, method: str = "", ran_before: bool = False,
                  silent_at_send_s: float = 0.0) -> None:
        """The first sight of a running script's end: what this host knew then. From a
        control call (``method``) that found it ended, or from the kicker."""
        with self._end_lock:
            if not self.script_live:
                return  # noted already, or not seen running since the last upload
            self.script_live = False
            allowed_s = self._allowed_s()
        now = time.monotonic()
        withheld = 0.0 if self.withheld_since_s is None else now - self.withheld_since_s
        if withheld < KICK_PERIOD_S:  # not one kick was withheld
            withheld = 0.0
        silent = max(self._silent_s(), silent_at_send_s)
        cause: Literal["watchdog", "command", "unknown"]
        if 0.0 < allowed_s < silent:
            cause = "watchdog"
        elif ran_before:  # it ran when the command was sent, and not after
            cause = "command"
        else:
            cause = "unknown"
        self.script_end = ScriptEnd(cause, now, silent, allowed_s, withheld, method)

    def create(self, name: ClientName) -> None:
        import dashboard_client
        import rtde_control
        import rtde_receive

        factories = {"dash": dashboard_client.DashboardClient,
                     "recv": rtde_receive.RTDEReceiveInterface,
                     "ctrl": rtde_control.RTDEControlInterface}
        with timer_slack(TIMER_SLACK_S[name]):  # the client's threads start in here
            if name == "recv":  # the adapter needs no more than this; fewer packages to parse
                self.objects[name] = factories[name](self.host, RECV_FREQUENCY_HZ)
            else:
                self.objects[name] = factories[name](self.host)

    def call(self, name: ClientName, method: str, args: tuple[Any, ...]) -> Any:
        obj = self.objects.get(name)
        if obj is None:
            raise RuntimeError(f"no {name} client")
        with self.locks[name]:  # one call at a time per client object
            ran_before = False
            silent_s = self._silent_s()
            if name == "ctrl":
                self._rate_before(obj, method)
                with contextlib.suppress(Exception):
                    ran_before = bool(obj.isProgramRunning())
                if ran_before:
                    with self._end_lock:
                        self.script_live = True
            try:
                result = getattr(obj, method)(*args)
            finally:
                if name == "ctrl":
                    self.ctrl_ended_s = time.monotonic()
                    self.last_call_streamed = method in STREAMED_METHODS
                    if method in STREAMED_METHODS or method in ENDS_STREAM:
                        self.streaming = method in STREAMED_METHODS
            # still holding the client: the kicker leaves a refused call's end to it
            if name == "ctrl" and result is False and method in COMMANDS_SCRIPT_RUNS:
                self._refused(obj, method, ran_before, silent_s)
        if name == "ctrl" and method in ENDS_STREAM and method not in PLANNED_MOVES:
            self._rate_after_stop(obj)
        if name == "ctrl" and method not in STREAMED_METHODS:
            self.call_ended.set()  # the kicker kicks now, not a tick later
        if name == "ctrl" and method == "reuploadScript" and result:
            with self._end_lock:
                self.script_live = False  # until seen running (the stream may still say ended)
                self.guarded_hz = 0.0  # a new script starts without a watchdog
            self.arm_watchdog()
        return result

    def _refused(self, ctrl: Any, method: str, ran_before: bool, silent_s: float) -> None:
        """A command the script runs said False: when the script has ended (the control or
        the receive client's view, which may lag the answer by a few cycles), note how."""
        deadline = time.monotonic() + SCRIPT_END_SEEN_S
        with contextlib.suppress(Exception):
            while bool(ctrl.isProgramRunning()) and self._script_running():
                if time.monotonic() > deadline:
                    return  # refused by a script that still runs
                time.sleep(0.002)
            self._note_end(method, ran_before, silent_s)

    def _rate_before(self, ctrl: Any, method: str) -> None:
        """The watchdog's rate for what comes: the streaming rate before a streamed command
        (a frozen host must stop the arm within 1 / min_frequency_hz), the low rate before a
        planned move (caller holds the control lock)."""
        guard = self.guard
        if guard is None or not self.watchdog_armed or method == "kickWatchdog":
            return
        if method in STREAMED_METHODS:
            want = guard.min_frequency_hz
        elif method in PLANNED_MOVES:
            want = guard.planned_frequency_hz
        else:
            return
        if want != self.armed_hz:
            with contextlib.suppress(Exception):
                self._set_rate(ctrl, want)

    def _rate_after_stop(self, ctrl: Any) -> None:
        """A stop has been sent and answered: nothing streams now, the low rate again."""
        guard = self.guard
        if guard is None or not self.watchdog_armed or self.armed_hz == guard.planned_frequency_hz:
            return
        with self.locks["ctrl"], contextlib.suppress(Exception):
            self._set_rate(ctrl, guard.planned_frequency_hz)

    def sample(self) -> StateSample:
        """Everything the adapter watches, read from the clients' cached state."""
        recv = self.objects.get("recv")
        if recv is None:
            raise RuntimeError("no receive client")
        with self._seq_lock:
            seq = next(self._seq)
        timestamp_s = float(recv.getTimestamp())
        seen_s = self._note_seen(timestamp_s)
        running, progress = False, -1
        ctrl = self.objects.get("ctrl")
        if ctrl is not None:
            status = ctrl.getAsyncOperationProgressEx()
            running, progress = bool(status.isAsyncOperationRunning()), int(status.progress())
        return StateSample(
            connected=bool(recv.isConnected()),
            timestamp_s=timestamp_s,
            tcp_pose=tuple(recv.getActualTCPPose()),
            q_rad=tuple(recv.getActualQ()),
            qd_rad_s=tuple(recv.getActualQd()),
            robot_mode=int(recv.getRobotMode()),
            safety_mode=int(recv.getSafetyMode()),
            safety_bits=int(recv.getSafetyStatusBits()),
            runtime_state=int(recv.getRuntimeState()),
            async_running=running,
            async_progress=progress,
            seq=seq,
            seen_s=seen_s,
        )

    def _note_seen(self, timestamp_s: float) -> float:
        with self._seq_lock:
            if timestamp_s != self._seen[0]:
                self._seen = (timestamp_s, time.monotonic())
            return self._seen[1]

    def handle(self, req: Request) -> Any:
        if isinstance(req, Create):
            return self.create(req.client)
        if isinstance(req, Sample):
            return self.sample()
        if isinstance(req, Drop):
            self.objects.pop(req.client, None)
            return None
        if isinstance(req, Subscribe):
            self.push_period_s = max(0.001, float(req.period_s))
            return None
        if isinstance(req, Guard):
            self.guard = req
            self.arm_watchdog()
            return None
        if isinstance(req, LastScriptEnd):
            return self.script_end
        return self.call(req.client, req.method, req.args)

    def data_key(self) -> tuple[float, bool] | None:
        """What tells whether the RTDE data changed (cheap: two reads), None without a
        receive client."""
        recv = self.objects.get("recv")
        if recv is None:
            return None
        timestamp_s = float(recv.getTimestamp())
        self._note_seen(timestamp_s)
        return timestamp_s, bool(recv.isConnected())


class _PushState:
    """Which samples the pusher sends: every change of the arm's state, and a still arm's
    samples only every ``QUIET_PUSH_S``.

    The parent would take 125 identical samples a second from a standing arm (2.4 % of a core
    for unpickling and the pose history). Held back instead, the last of them is sent just
    before the first sample that differs, so the parent's pose history still knows the arm
    stood until then and latency compensation interpolates nothing across the hold. Joint
    and TCP values within a deadband count as the same, so encoder noise of a real arm does
    not defeat this; a slow creep is still sent once it adds up to the deadband.
    """

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._last: StateSample | None = None  # the last sample sent
        self._last_s = 0.0
        self._held: StateSample | None = None  # the newest one not sent
        self._active_s = 0.0  # when the state last changed or a call was made

    def resting(self, now_s: float) -> bool:
        """The arm has not changed and no call was made for ``RESTING_AFTER_S``."""
        with self._lock:
            return now_s - self._active_s > RESTING_AFTER_S

    def due(self, now_s: float, period_s: float | None) -> bool:
        with self._lock:
            return period_s is not None and now_s - self._last_s >= period_s

    def take_held(self, now_s: float) -> StateSample | None:
        """The held sample, to go out now (before the answer to a :class:`Sample` request, so
        the parent's pose history knows the arm still stood when that sample was taken)."""
        with self._lock:
            held, self._held = self._held, None
            if held is not None:
                self._last, self._last_s = held, now_s
            return held

    def pushed(self, sample: StateSample, now_s: float) -> None:
        """``sample`` went to the parent outside the pusher (after a call)."""
        with self._lock:
            self._last, self._last_s, self._held = sample, now_s, None
            self._active_s = now_s

    def offer(self, sample: StateSample, now_s: float) -> list[StateSample]:
        """The samples to send now for a new package, oldest first."""
        with self._lock:
            last = self._last
            same = last is not None and unchanged(last, sample)
            if same and now_s - self._last_s < QUIET_PUSH_S:
                self._held = sample
                return []
            if not same:
                self._active_s = now_s
            out = [sample]
            if self._held is not None and not unchanged(self._held, sample):
                out.insert(0, self._held)
            self._last, self._last_s, self._held = sample, now_s, None
            return out


def unchanged(a: StateSample, b: StateSample) -> bool:
    """The same arm state for the adapter: modes, bits and async state equal, joints and TCP
    within the deadband (only the package's timestamp moved on)."""
    return (a.connected == b.connected and a.robot_mode == b.robot_mode
            and a.safety_mode == b.safety_mode and a.safety_bits == b.safety_bits
            and a.runtime_state == b.runtime_state and a.async_running == b.async_running
            and a.async_progress == b.async_progress
            and _within(a.q_rad, b.q_rad, STILL_DEADBAND_RAD)
            and _within(a.qd_rad_s, b.qd_rad_s, STILL_DEADBAND_RAD_S)
            and _within(a.tcp_pose, b.tcp_pose, STILL_DEADBAND_M_RAD))


def _within(a: tuple[float, ...], b: tuple[float, ...], tol: float) -> bool:
    return len(a) == len(b) and all(abs(x - y) <= tol for x, y in zip(a, b, strict=True))


def _bind_to_parent() -> None:
    """The child dies with its parent (Linux: PR_SET_PDEATHSIG) and ignores the terminal's
    Ctrl-C: the parent stops the arm first and then closes this process itself."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    if sys.platform.startswith("linux"):
        with contextlib.suppress(OSError, AttributeError):
            ctypes.CDLL(None, use_errno=True).prctl(PR_SET_PDEATHSIG, signal.SIGKILL, 0, 0, 0)


def child_main(host: str, parent_pid: int | None = None) -> None:
    """Serve requests from stdin until it closes; replies go to stdout."""
    _bind_to_parent()
    if parent_pid is not None and os.getppid() != parent_pid:
        os._exit(0)  # the parent died before the death signal was set
    stdin = sys.stdin.buffer
    # ur_rtde prints to file descriptor 1: keep the reply stream on a private copy of it and
    # send fd 1 (and Python's stdout) to stderr.
    stdout = os.fdopen(os.dup(1), "wb")
    os.dup2(2, 1)
    sys.stdout = sys.stderr
    clients = _Clients(host)
    lock = threading.Lock()

    pusher_state = _PushState()
    wake_pusher = threading.Event()  # a call was made: look at the arm at full rate again
    # a held sample and the pusher's next one go out in the order they were taken
    push_order = threading.Lock()

    def send(sample: StateSample) -> None:
        with contextlib.suppress(OSError, ValueError):
            _write(stdout, (PUSH_ID, True, sample), lock)

    def push() -> None:
        """One sample to the parent now, when subscribed and there is something to sample."""
        if clients.push_period_s is None:
            return
        try:
            sample = clients.sample()
        except Exception:  # no receive client (yet, or any more): nothing to push
            return
        with push_order:
            pusher_state.pushed(sample, time.monotonic())
            send(sample)

    def serve(req_id: int, req: Request) -> None:
        try:
            reply: tuple[Any, ...] = (req_id, True, clients.handle(req))
        except Exception as exc:
            reply = (req_id, False, (type(exc).__name__, str(exc)))
        if isinstance(req, Call):
            push()  # before the reply: what the parent reads next reflects the call
            wake_pusher.set()
        elif isinstance(req, Sample) and clients.push_period_s is not None:
            with push_order:  # the still arm's held sample first (see _PushState.take_held)
                held = pusher_state.take_held(time.monotonic())
                if held is not None:
                    send(held)
        with contextlib.suppress(OSError, ValueError):
            _write(stdout, reply, lock)
        if isinstance(req, Subscribe):
            threading.Thread(target=pusher, daemon=True, name="pusher").start()

    def pusher() -> None:
        """Look whether the RTDE data changed every ``PUSH_CHECK_S`` (``RESTING_CHECK_S``
        while the arm rests), and push when it did, at most once per subscribed period; a
        still arm's samples only every ``QUIET_PUSH_S`` (see :class:`_PushState`)."""
        last: tuple[float, bool] | None = None
        set_timer_slack(PUSHER_TIMER_SLACK_S)
        while True:
            resting = pusher_state.resting(time.monotonic())
            if wake_pusher.wait(RESTING_CHECK_S if resting else PUSH_CHECK_S):
                wake_pusher.clear()
            try:
                key = clients.data_key()
            except Exception:
                key = None
            now = time.monotonic()
            if key is None or key == last or not pusher_state.due(now, clients.push_period_s):
                continue
            last = key
            try:
                sample = clients.sample()
            except Exception:
                continue
            with push_order:
                for out in pusher_state.offer(sample, now):
                    send(out)

    def kicker() -> None:
        """Kick the controller's watchdog while the parent lives (see Guard)."""
        set_timer_slack(PUSHER_TIMER_SLACK_S)
        while True:
            if clients.call_ended.wait(KICK_PERIOD_S):
                clients.call_ended.clear()
            if parent_pid is not None and os.getppid() != parent_pid:
                os._exit(0)  # orphaned: the controller's watchdog stops the arm
            clients.kick()

    threading.Thread(target=kicker, daemon=True, name="kicker").start()
    while True:
        try:
            req = _read(stdin)
        except (EOFError, OSError):
            break
        clients.parent_seen_s = time.monotonic()
        if isinstance(req[1], Heartbeat):
            continue
        threading.Thread(target=serve, args=req, daemon=True).start()
    stdout.flush()
    os._exit(0)  # skip ur_rtde destructors: the parent has already closed what it wanted


# -- the parent ------------------------------------------------------------------------------

class ClientProcess:
    """A child process holding the ur_rtde clients of one controller."""

    def __init__(self, host: str) -> None:
        self.host = host
        self._proc = subprocess.Popen(
            [sys.executable, "-m", "drivers.ur.client_process", host, str(os.getpid())],
            stdin=subprocess.PIPE, stdout=subprocess.PIPE,
            process_group=0)  # the terminal's Ctrl-C goes to the parent, which stops the arm
        self._ids = itertools.count(1)
        self._pending: dict[int, Future[Any]] = {}
        self._lock = threading.Lock()
        self._write_lock = threading.Lock()  # one frame at a time into the request pipe
        assert self._proc.stdin is not None
        self._stdin_fd = self._proc.stdin.fileno()
        os.set_blocking(self._stdin_fd, False)  # every write has a deadline (_send)
        self._stdin_closed = False
        self.dead_reason: str | None = None
        # told of every pushed sample (see Subscribe), from the reader thread
        self.on_push: Callable[[StateSample], None] | None = None
        threading.Thread(target=self._read_replies, daemon=True,
                         name=f"ur-client-{host}").start()
        threading.Thread(target=self._heartbeat, daemon=True,
                         name=f"ur-heartbeat-{host}").start()

    def _send(self, obj: object, timeout_s: float) -> None:
        """One frame to the child within ``timeout_s`` (TimeoutError when it does not take
        it: the caller kills it); OSError when the pipe is closed."""
        data = pickle.dumps(obj)
        frame = _LEN.pack(len(data)) + data
        deadline_s = time.monotonic() + timeout_s
        if not self._write_lock.acquire(timeout=timeout_s):
            raise TimeoutError("another request is still being written")
        try:
            if self._stdin_closed:
                raise OSError("the request pipe is closed")
            _write_within(self._stdin_fd, frame, deadline_s)
        finally:
            self._write_lock.release()

    def _heartbeat(self) -> None:
        """Tell the child this process lives (it kicks the controller's watchdog only then)."""
        while self.dead_reason is None:
            try:
                self._send((0, Heartbeat()), HEARTBEAT_WRITE_S)
            except TimeoutError:
                self.kill(f"the ur_rtde client process took no request for "
                          f"{HEARTBEAT_WRITE_S:g} s")
                return
            except (OSError, ValueError):
                return
            time.sleep(HEARTBEAT_S)

    def _read_replies(self) -> None:
        assert self._proc.stdout is not None
        while True:
            try:
                req_id, ok, value = _read(self._proc.stdout)
            except (EOFError, OSError, pickle.UnpicklingError):
                break
            if req_id == PUSH_ID:
                on_push = self.on_push
                if on_push is not None and ok:
                    try:
                        on_push(value)
                    except Exception:  # the reader must outlive a bad consumer
                        logging.getLogger(__name__).exception("pushed sample not taken")
                continue
            with self._lock:
                fut = self._pending.pop(req_id, None)
            if fut is not None:
                if ok:
                    fut.set_result(value)
                else:
                    fut.set_exception(RemoteError(*value))
        code = self._proc.poll()
        self._die(f"the ur_rtde client process ended (exit code {code})")
        with contextlib.suppress(OSError):
            self._proc.stdout.close()  # the reader owns its pipe: a replaced child leaves none

    def _die(self, reason: str) -> None:
        with self._lock:
            if self.dead_reason is None:
                self.dead_reason = reason
            pending, self._pending = self._pending, {}
        for fut in pending.values():
            fut.set_exception(ClientDied(reason))

    def request(self, req: Request, timeout_s: float = 3.0) -> Any:
        """Run one request in the child; ClientDied when it is gone or overruns the deadline
        (the child is then killed: a client that hung once is not trusted again)."""
        fut: Future[Any] = Future()
        with self._lock:
            if self.dead_reason is not None:
                raise ClientDied(self.dead_reason)
            req_id = next(self._ids)
            self._pending[req_id] = fut
        try:
            self._send((req_id, req), timeout_s)
        except TimeoutError:
            self.kill(f"{describe(req)}: the ur_rtde client process did not take the request "
                      f"within {timeout_s:g} s")
            raise ClientDied(self.dead_reason or "timeout") from None
        except (OSError, ValueError) as exc:
            self._die(f"cannot reach the ur_rtde client process: {exc}")
        try:
            return fut.result(timeout=timeout_s)
        except FutureTimeout:
            self.kill(f"{describe(req)}: no answer from the controller within {timeout_s:g} s")
            raise ClientDied(self.dead_reason or "timeout") from None

    def kill(self, reason: str) -> None:
        """End the child and close this side's request pipe (the reader closes the reply
        pipe when it sees the end): a cell that replaces its child for months keeps no
        descriptors of the old ones."""
        self._die(reason)
        if self._proc.poll() is None:
            self._proc.kill()
        with contextlib.suppress(subprocess.TimeoutExpired):
            self._proc.wait(timeout=2.0)
        self._close_stdin()

    def _close_stdin(self) -> None:
        """Close the request pipe once no frame is being written into it (a writer ends by
        its deadline, or at once when the child is gone)."""
        locked = self._write_lock.acquire(timeout=HEARTBEAT_WRITE_S + 1.0)
        try:
            self._stdin_closed = True
            if self._proc.stdin is not None:
                with contextlib.suppress(OSError):
                    self._proc.stdin.close()
        finally:
            if locked:
                self._write_lock.release()

    def close(self, timeout_s: float = 2.0) -> None:
        """Let the child exit (stdin closed); kill it if it does not."""
        self._close_stdin()
        try:
            self._proc.wait(timeout=timeout_s)
        except subprocess.TimeoutExpired:
            self._proc.kill()
            self._proc.wait(timeout=2.0)
        self._die("closed")


if __name__ == "__main__":
    # Run the importable module's copy, so the message classes the parent pickles (by their
    # module name) are the very ones ``handle`` checks against.
    from drivers.ur.client_process import child_main as _child_main

    _child_main(sys.argv[1], int(sys.argv[2]) if len(sys.argv) > 2 else None)
