"""What a closed loop's runner asks of its law, and what a law may ask of the runner.

A law holds what its control is made of and decides per frame what a measurement is, per tick
where to go, the twist and whether it has converged; the runner
(:mod:`~cell.servoing.runner`) owns the threads and the clocks, as the caller of ViSP's
``vpServo`` owns the loop while ``vpServo`` holds the features and the gain. Per frame (frame
thread): :meth:`Law.read` outside the runner's lock, :meth:`Law.admit` under it; either may
refuse (:class:`Unusable`). Per tick (control loop): :meth:`Law.aim` under the lock,
:meth:`Law.judge`, :meth:`Law.twist`. With the arm stopped: :meth:`Law.settle`,
:meth:`Law.result`.
"""

from __future__ import annotations

import threading
from dataclasses import dataclass, field
from typing import Any, Generic, Literal, Protocol, TypeVar

import numpy as np
from numpy.typing import NDArray

from cell.config.schema import CellConfig
from cell.core import CellCore
from cell.errors import CellError
from cell.motion.guard import Motion
from cell.servoing.clock import TwistClock
from cell.servoing.record import FrameStats, History
from cell.servoing.target_loss import Silence
from cell.vision.locate import Located
from drivers.arm import ArmState

Matrix4 = NDArray[np.float64]
Vec = NDArray[np.float64]
LoopMode = Literal["approach", "track"]  # converge and stop, or follow for a duration
M = TypeVar("M")  # a measurement, as the law keeps it
A = TypeVar("A")  # what the law aims at on one tick
M_co = TypeVar("M_co", covariant=True)


class Unusable(Exception):
    """A frame that gives no measurement: ``error`` why; ``failed`` counted among the frames
    without the target (a law counts its own kinds, such as the gate's jumps)."""

    def __init__(self, error: CellError | None, failed: bool = True) -> None:
        super().__init__(error)
        self.error, self.failed = error, failed


@dataclass(frozen=True)
class Tick(Generic[M]):
    t: float  # time.monotonic()
    silence: Silence  # the lost-target clock's
    frames: int  # measurements taken so far: a new one when it changes
    newest: M | None
    camera_running: bool  # frames arrive and are examined
    why_unseen: CellError | None  # why the last frame gave no measurement


@dataclass(frozen=True)
class Reading:
    """A measurement judged: its errors (a history row, shown in the progress and ``servo``
    events), more for the progress, and whether the loop has converged."""

    errors: dict[str, float]
    converged: bool = False
    shown: dict[str, Any] = field(default_factory=dict)


@dataclass(frozen=True)
class StreamCaps:
    """The ``[servo]`` speeds and accelerations of a streamed twist, capped by ``[limits]``."""

    max_speed_mm_s: float
    max_rate_rad_s: float
    accel_mm_s2: float
    accel_rad_s2: float

    @classmethod
    def of(cls, config: CellConfig) -> StreamCaps:
        sc, lim = config.servo, config.limits
        return cls(min(sc.max_speed_mm_s, lim.max_speed_mm_s),
                   float(np.radians(min(sc.max_angular_speed_deg_s,
                                        lim.max_angular_speed_deg_s))),
                   min(sc.accel_mm_s2, lim.max_accel_mm_s2),
                   float(np.radians(min(sc.angular_accel_deg_s2,
                                        lim.max_angular_accel_deg_s2))))


class Loop(Protocol[M_co]):
    core: CellCore
    motion: Motion
    lock: threading.Lock  # guards what the frame thread writes
    stats: FrameStats
    history: History
    t0: float  # the control loop's start (time.monotonic())

    def stop(self) -> float:
        """Stop the arm and wait until it stands; the seconds it took."""

    def newest(self) -> M_co | None:
        """The newest measurement taken."""


class Law(Protocol[M, A]):
    name: str  # in messages: "servo", "IBVS"
    mode: LoopMode
    doing: str  # where a stop finds it ("while servoing")
    phase: str  # the job's progress phase
    event_mode: str  # the ``servo`` events' mode
    unseen: str  # the lost-target message's "after the last ..."
    blind_frames_examined: bool  # frames the estimator finds no target in run the lost clock
    timeout_s: float  # an approach not converged by then fails
    caps: StreamCaps

    def seed(self, first: Located) -> M | None:
        """The job's own locate: the law starts from it (None) or takes it as its first
        measurement."""

    def read(self, located: Located) -> M:
        """A located frame as a measurement."""

    def admit(self, measurement: M) -> None:
        """Take a measurement (under the runner's lock)."""

    def aim(self, now: Tick[M]) -> A | None:
        """Where to go on this tick (under the lock); None: nowhere (no measurement, or the
        target lost). A CellError ends the run, the arm stopped first."""

    def judge(self, aim: A, T_tcp: Matrix4, new: bool, t_s: float, prev: Vec
              ) -> Reading | None:
        """The TCP against the aim (``new``: a measurement not judged yet; ``prev``: the
        twist last sent); None: nothing to judge by."""

    def twist(self, aim: A, T_tcp: Matrix4, state: ArmState, t: float, clock: TwistClock
              ) -> Vec:
        """The TCP's base-frame twist to send now (its step: :meth:`TwistClock.step`)."""

    def left(self) -> str:
        """The error left, for a timeout's message."""

    def lost_detail(self, stats: FrameStats) -> str:
        """The law's own counts of frames it did not use, for the lost-target message."""

    def settle(self, loop: Loop[M], converged_s: float | None) -> float | None:
        """The law's last steps, if it has any; when it converged (s)."""
        return converged_s

    def result(self, loop: Loop[M], reached: Matrix4) -> dict[str, Any]:
        """The law's part of the job's result."""
