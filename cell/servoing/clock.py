"""The twist a loop last sent and when: where the TCP is now, and the next twist's step."""

from __future__ import annotations

import time

import numpy as np
from numpy.typing import NDArray

from cell.motion.guard import SERVO_MIN_DT_S, GuardedArm
from cell.motion.twist import extrapolate_tcp
from drivers.arm import ArmState

Matrix4 = NDArray[np.float64]
MAX_EXTRAPOLATE_S = 0.05  # an arm state older than this is moved on by this much only


class TwistClock:
    """``prev``: the twist last sent (zero before the first, and after a tick late enough for
    the arm's watchdog to have braked it)."""

    def __init__(self, arm: GuardedArm, tick_s: float, watchdog_s: float) -> None:
        self._arm, self.tick_s, self.watchdog_s = arm, tick_s, watchdog_s
        self.prev: NDArray[np.float64] = np.zeros(6)
        self._t_prev: float | None = None  # when it was sent
        self._t_cmd = 0.0

    def tcp_now(self, state: ArmState, tick_s: float) -> Matrix4:
        """The TCP now: the reading (a few ms old) moved on by the twist last sent, for as
        long as the arm kept that twist (its watchdog brakes it after ``watchdog_s``)."""
        held_s = 0.0 if self._t_prev is None else min(tick_s, self._t_prev + self.watchdog_s) \
            - state.timestamp_s
        return extrapolate_tcp(state.T_base_tcp, self.prev,
                               min(max(held_s, 0.0), MAX_EXTRAPOLATE_S))

    def step(self) -> float:
        """The time the law may change the twist over (s), taken just before it does: since
        the guard accepted the last tick, which the guard (judging by its own clock, ticks at
        least ``SERVO_MIN_DT_S`` apart) sees as at least as long; capped at two ticks. (One
        nominal tick per tick lost a sixth of the acceleration: ticks come every ~9.5 ms.)"""
        t_cmd = time.monotonic()
        accepted_s = self._arm.last_twist_s
        dt = SERVO_MIN_DT_S if self._t_prev is None or accepted_s is None else min(
            max(t_cmd - accepted_s, SERVO_MIN_DT_S), 2.0 * self.tick_s)
        if self._t_prev is not None and t_cmd - self._t_prev > 0.75 * self.watchdog_s:
            self.prev = np.zeros(6)  # a late tick: the arm's watchdog may have braked it
        self._t_cmd = t_cmd
        return dt

    def sent(self, twist: NDArray[np.float64]) -> None:
        self.prev, self._t_prev = twist, self._t_cmd
