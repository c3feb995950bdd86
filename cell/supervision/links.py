"""Links that come back: watch the arm and camera, fail what depends on a lost one, reconnect.

The service starts whatever is reachable and serves anyway (``/health`` says ``degraded`` and
names what is missing). ``cell serve`` does not even wait for the first try: the HTTP API
answers while the arm connects and powers on (a real arm's power-on and brake release take
seconds), and ``/health`` says ``starting`` until that first try has ended. A background
thread checks each link every ``CHECK_PERIOD_S``:

- a link that drops fails the running job that needs it (``arm_disconnected``,
  ``camera_lost``) and is logged and published once;
- a lost link is tried again with exponential backoff (``[robot] reconnect_initial_s`` up to
  ``reconnect_max_s``), every try logged; the UR adapter's connect tells the controller to stop
  before anything else, so a move it kept running while the link was down ends at once;
- a link that is back is made ready as at start: the TCP set and, with
  ``[robot] power_on_at_start``, the arm powered on.
"""

from __future__ import annotations

import logging
import threading
import time
from dataclasses import dataclass

from cell.core import CellCore
from cell.error_codes import ErrorCode
from cell.errors import CellError, UnavailableError
from cell.supervision.startup import Startup
from drivers.errors import DriverError

log = logging.getLogger(__name__)
CHECK_PERIOD_S = 0.1
STARTUP_PART = "arm and camera"


@dataclass
class LinkState:
    """One device's link as the supervisor sees it."""

    name: str
    up: bool = False
    tries: int = 0  # failed tries since it was last up
    next_try_s: float = 0.0
    backoff_s: float = 0.0
    last_error: str | None = None
    since_s: float = 0.0  # time.monotonic() of the last change

    def as_dict(self, now_s: float) -> dict[str, object]:
        return {"up": self.up, "tries": self.tries, "last_error": self.last_error,
                "retry_in_s": None if self.up else max(0.0, self.next_try_s - now_s),
                "for_s": max(0.0, now_s - self.since_s)}


class LinkSupervisor:
    def __init__(self, core: CellCore, startup: Startup | None = None) -> None:
        self.core = core
        self.startup = startup if startup is not None else Startup()
        rc = core.config.robot
        self.initial_s, self.max_s = rc.reconnect_initial_s, max(rc.reconnect_max_s,
                                                                 rc.reconnect_initial_s)
        now = time.monotonic()
        self.arm = LinkState("arm", since_s=now, backoff_s=self.initial_s)
        self.camera = LinkState("camera", since_s=now, backoff_s=self.initial_s)
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._lock = threading.Lock()

    # -- start --------------------------------------------------------------------------------
    def connect_all(self) -> None:
        """One try at each device, at start; what fails is retried in the background."""
        try:
            self.core.hw.wait_ready()
        except Exception as err:  # the tries below fail and say how; the retries go on
            log.error("a simulated device did not start: %s", err)
        self._try_arm(first=True)
        self._try_camera(first=True)

    def start(self, first_tries: bool = False) -> None:
        """Supervise in the background; ``first_tries``: make the start's one try at each
        device there too (instead of :meth:`connect_all` before this), so the caller serves
        at once and :attr:`starting` is true until those tries have ended."""
        if first_tries:
            self.startup.begin(STARTUP_PART)
        self._thread = threading.Thread(target=self._loop, args=(first_tries,),
                                        name="cell-links", daemon=True)
        self._thread.start()

    @property
    def starting(self) -> bool:
        """The start's first tries at the devices are still running."""
        return STARTUP_PART in self.startup.running

    def close(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=5.0)

    def missing(self) -> list[str]:
        """Devices not connected now: the supervisor's view, and the devices' own (which
        may know of a loss a check period before the supervisor does)."""
        try:
            arm_now = self.core.arm.state().connected
        except DriverError:
            arm_now = False
        camera_now = bool(self.core.camera.is_connected)
        with self._lock:
            return [s.name for s, now in ((self.arm, arm_now), (self.camera, camera_now))
                    if not (s.up and now)]

    def snapshot(self) -> dict[str, dict[str, object]]:
        now = time.monotonic()
        with self._lock:
            return {"arm": self.arm.as_dict(now), "camera": self.camera.as_dict(now)}

    # -- the loop ----------------------------------------------------------------------------
    def _loop(self, first_tries: bool) -> None:
        if first_tries:
            try:
                self.connect_all()
            except Exception:  # a failed try is retried below like any lost link
                log.exception("the first connect at start failed")
            finally:
                self.startup.end(STARTUP_PART)
        while not self._stop.wait(CHECK_PERIOD_S):
            try:
                self._check_arm()
                self._check_camera()
            except Exception:  # the supervisor itself must never die
                log.exception("link supervisor check failed")

    def _check_arm(self) -> None:
        try:
            connected = self.core.arm.state().connected
        except DriverError:
            connected = False
        if self.arm.up and not connected:
            self._lost(self.arm, UnavailableError(
                ErrorCode.arm_disconnected, "the link to the arm's controller was lost; the cell "
                "reconnects by itself and tells the arm to stop first"), needs_camera=False)
        elif not self.arm.up and time.monotonic() >= self.arm.next_try_s:
            self._try_arm(first=False)

    def _check_camera(self) -> None:
        connected = bool(self.core.camera.is_connected)
        if self.camera.up and not connected:
            self._lost(self.camera, UnavailableError(
                ErrorCode.camera_lost, "the camera was lost; the cell reconnects by itself"),
                needs_camera=True)
        elif not self.camera.up and connected:
            self._up(self.camera)  # came back on its own (the OAK adapter reconnects itself)
        elif not self.camera.up and time.monotonic() >= self.camera.next_try_s:
            self._try_camera(first=False)

    def _lost(self, link: LinkState, reason: UnavailableError, needs_camera: bool) -> None:
        with self._lock:
            link.up, link.since_s, link.last_error = False, time.monotonic(), reason.message
            link.backoff_s, link.next_try_s = self.initial_s, time.monotonic() + self.initial_s
        log.warning("%s link lost", link.name)
        motion = self.core.slot.current
        if motion is not None and (not needs_camera or motion.needs_camera):
            motion.cancel_with(reason)
            if link.name == "camera":
                self.core.arm.settle()  # the job's next look would be blind: stop now
        self.core.events.publish("link", {"device": link.name, "up": False,
                                          "reason": reason.message})

    def _up(self, link: LinkState) -> None:
        with self._lock:
            link.up, link.since_s, link.tries, link.last_error = True, time.monotonic(), 0, None
            link.backoff_s = self.initial_s
        self.core.stats.count_reconnect(link.name)
        log.info("%s link up", link.name)
        self.core.events.publish("link", {"device": link.name, "up": True})

    def _failed_try(self, link: LinkState, err: Exception) -> None:
        with self._lock:
            link.tries += 1
            link.last_error = str(err)
            link.next_try_s = time.monotonic() + link.backoff_s
            delay, link.backoff_s = link.backoff_s, min(self.max_s, link.backoff_s * 2.0)
        log.warning("%s: connect try %d failed: %s; next try in %.1f s", link.name, link.tries,
                    err, delay)

    def _try_arm(self, first: bool) -> None:
        """Connect (the adapter stops the controller first) and make the arm ready as at
        start, holding the motion slot throughout: nothing may move on a half-prepared link
        (a TCP not yet set would make every pose wrong by the tool's length)."""
        slot = self.core.slot
        try:
            motion = slot.claim("start" if first else "reconnect")
        except CellError:
            return  # a job still ends on the old link; try on the next check
        try:
            arm = self.core.arm.raw
            try:
                reconnect = getattr(arm, "reconnect", None)
                if first or reconnect is None:
                    arm.connect()
                else:
                    reconnect()
            except DriverError as err:
                self._failed_try(self.arm, err)
                return
            try:  # readiness is not the link: a stopped or unpowered arm stays connected
                if self.core.config.robot.power_on_at_start:
                    arm.power_on()
                if arm.state().ready:
                    arm.set_tcp(self.core.frames.T_flange_tcp)
            except DriverError as err:
                log.warning("arm connected but not made ready: %s", err)
            self._up(self.arm)
        finally:
            slot.release(motion)

    def _try_camera(self, first: bool) -> None:
        try:
            self.core.camera.connect()
            if not self.core.camera.is_connected:
                raise UnavailableError(ErrorCode.camera_lost, "connected, but no frames flow yet")
        except (DriverError, UnavailableError) as err:
            self._failed_try(self.camera, err)
            return
        self._up(self.camera)
