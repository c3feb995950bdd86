"""One snapshot of the cell behind every read, never much older than a camera period.

``/status``, ``/health``, the SSE ``state`` event and the metrics gauges all come from the
newest :class:`Snap`, so a read costs a dictionary lookup (and the HTTP answer is JSON encoded
once per refresh, not once per client), and no read ever waits on a device: the snapshot is
built from the adapters' cached state (see :mod:`cell.supervision.status`).

Fresh enough for anyone: a reader that finds it older than 1.5 periods, or taken before the
motion slot last changed hands (a jog step or a job that just ended), refreshes it on the spot;
concurrent readers share that one refresh instead of each building their own. A background
thread refreshes it ahead, every camera period, only while that saves work: while SSE clients
listen, or while more than ``DENSE_READS_PER_PERIOD`` reads come per period (a crowd of
pollers). A sparse reader (the OPC UA server's 10 Hz update, the alarm watch, an operator
page polling at 4 Hz) would find a refresh made ahead already stale, so it refreshes on its
own and an idle service builds nothing it does not hand out. An event loop never waits for a
refresh (:meth:`CellSnapshot.fresh`): it hands a late one to a worker thread.
"""

from __future__ import annotations

import json
import logging
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np

from cell.core import CellCore
from cell.supervision import status as status_mod
from cell.supervision.gripper import GripperService
from cell.supervision.links import LinkSupervisor
from cell.supervision.storage import StorageWatch

log = logging.getLogger(__name__)
MAX_RATE_HZ = 30.0  # a faster camera does not make the reports faster than this
# A reader takes a snapshot up to this many periods old: the refresh thread, late by a few ms
# on a loaded host, would otherwise send every read arriving just past one period to a
# worker thread for a refresh of its own.
READ_TOLERANCE_PERIODS = 1.5
# Refreshing ahead pays from this many reads per period on (a crowd of pollers); until then
# the thread only looks every IDLE_TICK_S whether it does.
DENSE_READS_PER_PERIOD = 2.0
IDLE_TICK_S = 0.1


def _plain(obj: Any) -> Any:
    """What json cannot encode by itself: numpy scalars and arrays."""
    if isinstance(obj, np.generic):
        return obj.item()
    if isinstance(obj, np.ndarray):
        return obj.tolist()
    raise TypeError(f"cannot encode {type(obj).__name__}")


def encode(obj: Any) -> bytes:
    return json.dumps(obj, default=_plain, separators=(",", ":")).encode()


@dataclass(frozen=True)
class Snap:
    taken_s: float  # time.monotonic() when it was built
    slot_generation: int
    status: dict[str, Any]
    health: dict[str, Any]
    state: dict[str, Any] | None  # the SSE ``state`` event's data (None: arm unreadable)
    status_json: bytes
    health_json: bytes

    def age_s(self, now_s: float | None = None) -> float:
        return max(0.0, (time.monotonic() if now_s is None else now_s) - self.taken_s)


def with_age(body: bytes, age_s: float) -> bytes:
    """``body`` (a JSON object) with ``snapshot_age_s`` added in front, without re-encoding."""
    return b'{"snapshot_age_s":' + f"{age_s:.4f}".encode() + (b"," if len(body) > 2 else b"") \
        + body[1:]


class CellSnapshot:
    def __init__(self, core: CellCore, links: LinkSupervisor, gripper: GripperService,
                 storage: StorageWatch | None = None,
                 starting: Callable[[], bool] | None = None,
                 reason_sources: list[Callable[[], list[dict[str, str]]]] | None = None
                 ) -> None:
        """``starting``: a part of the start still runs (default: the links' first tries);
        ``reason_sources``: more reasons for ``/health`` (the PLC servers'), read at each
        snapshot, so the list may grow after this."""
        self.core = core
        self.reason_sources = reason_sources if reason_sources is not None else []
        self.starting = starting if starting is not None else (lambda: links.starting)
        self.links = links
        self.gripper = gripper
        self.storage = storage
        self.period_s = 1.0 / min(core.config.camera.fps, MAX_RATE_HZ)
        self._snap: Snap | None = None
        self._reads = 0  # counted, not locked: a lost increment only delays a refresh ahead
        self._refresh_lock = threading.Lock()
        self._closing = threading.Event()
        self._thread: threading.Thread | None = None

    # -- lifecycle -------------------------------------------------------------------------------
    def start(self) -> None:
        self._thread = threading.Thread(target=self._loop, name="cell-snapshot", daemon=True)
        self._thread.start()

    def close(self) -> None:
        self._closing.set()
        if self._thread is not None:
            self._thread.join(timeout=2.0)

    # -- reads --------------------------------------------------------------------------------
    def current(self) -> Snap:
        """The newest snapshot, refreshed first when it is older than 1.5 periods or older
        than the last change of the motion slot."""
        self._reads += 1
        snap = self._snap
        if snap is None or self._stale(snap):
            return self.refresh(unless_newer_than=snap)
        return snap

    def fresh(self) -> Snap | None:
        """The newest snapshot when it needs no refresh, else None; never blocks (for an
        event loop, which must not wait for a refresh another thread is building)."""
        self._reads += 1
        snap = self._snap
        return None if snap is None or self._stale(snap) else snap

    def status(self) -> dict[str, Any]:
        snap = self.current()
        return {**snap.status, "snapshot_age_s": snap.age_s()}

    def health(self) -> dict[str, Any]:
        return dict(self.current().health)

    def _other_reasons(self) -> list[dict[str, str]]:
        out = [] if self.storage is None else self.storage.reasons()
        for source in list(self.reason_sources):
            try:
                out += source()
            except Exception:  # one broken source must not take /health down with it
                log.exception("a health reason source failed")
        return out

    def _stale(self, snap: Snap) -> bool:
        return (time.monotonic() - snap.taken_s > READ_TOLERANCE_PERIODS * self.period_s
                or snap.slot_generation != self.core.slot.generation)

    # -- building -------------------------------------------------------------------------------
    def refresh(self, unless_newer_than: Snap | None = None) -> Snap:
        """Build a new snapshot; when another thread built one while this one waited for
        the lock (newer than ``unless_newer_than``, and not stale), that one is returned."""
        with self._refresh_lock:
            snap = self._snap
            if snap is not None and snap is not unless_newer_than and not self._stale(snap):
                return snap
            snap = self._build()
            self._snap = snap
            return snap

    def _build(self) -> Snap:
        core = self.core
        generation = core.slot.generation  # before reading: a change meanwhile means stale
        now = time.monotonic()
        st = status_mod.status(core, self.links, self.gripper)
        missing = [name for name, link in st["links"].items() if not link["up"]]
        if not st["robot"].get("connected", False) and "arm" not in missing:
            missing.append("arm")
        if not st["camera"]["connected"] and "camera" not in missing:
            missing.append("camera")
        health = status_mod.health_from(
            missing, st["robot"], self._other_reasons(),
            starting=self.starting())
        robot = st["robot"]
        motion = core.slot.current
        state = None if "T_base_tcp" not in robot else {
            "state": st["state"], "robot_mode": robot["mode"], "safety": robot["safety"],
            "moving": robot["moving"], "T_base_tcp": robot["T_base_tcp"],
            "job_id": motion.job_id if motion else None,
            "camera_connected": st["camera"]["connected"],
        }
        return Snap(now, generation, st, health, state, encode(st), encode(health))

    def _loop(self) -> None:
        next_s = last_s = time.monotonic()
        seen_reads, ahead = self._reads, False
        while not self._closing.is_set():
            try:
                now = time.monotonic()
                reads, seen_reads = self._reads - seen_reads, self._reads
                rate_hz, last_s = reads / max(now - last_s, 1e-3), now
                listeners = self.core.events.n_subscribers
                ahead = bool(listeners) or rate_hz >= DENSE_READS_PER_PERIOD / self.period_s
                if ahead:
                    snap = self.refresh(unless_newer_than=self._snap)
                    if snap.state is not None and listeners:
                        self.core.events.publish("state", snap.state)
            except Exception:  # the reports must outlive any one bad read
                log.exception("snapshot refresh failed")
            next_s += self.period_s if ahead else IDLE_TICK_S
            delay = next_s - time.monotonic()
            if delay < -self.period_s:  # fell behind (loaded host): do not burst
                next_s, delay = time.monotonic(), 0.0
            if self._closing.wait(max(0.0, delay)):
                break
