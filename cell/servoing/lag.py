"""A track that has fallen behind its target: the cell cannot keep up, so it stops.

A conveyor faster than the arm may follow (its speed cap), or a host too loaded to send the
law's twists in time, leaves the TCP behind the moving goal by more and more, or swinging about
it; a track that went on would chase the target off its goal and out of the camera's view.
Once a track follows its goal (the RMS of its error under the limit over a whole window), or
``CATCH_UP_WINDOWS`` windows after its first error under the limit (the pull-in from wherever
it started, and the catching up with a conveyor that starts at speed, is an approach, not a
lag), the RMS of its error over the last ``track_lag_s`` over
``[servo] track_lag_mm`` ends it with the arm stopped (``tracking_lag``). An RMS rather than
every frame over the limit: a loop swinging about a lagging goal (a starved host's latency)
crosses back under the limit on some frames and would never end. Each error counts until the
next (a frame's error holds until the next frame). Judged on the loop's own estimate, the
error it acts on: frames are the evidence, so a gap between them is the lost-target clock's to
judge, not this one's.
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass
from itertools import pairwise

# after its first error under the limit, a track has this many windows to follow its goal (a
# whole window under the limit in RMS) before a window over it is a lag: the catching up
# with a conveyor that starts at speed (at 150 mm/s, 12-13 mm RMS a second after the first
# error under 10 mm, on a quiet host: the filter learns its speed over ~1 s)
CATCH_UP_WINDOWS = 8


@dataclass(frozen=True)
class Lag:
    """Why a track must end: its error's RMS over the last ``window_s``."""

    rms_mm: float
    window_s: float


class LagWatch:
    """Whether a track's error has stayed over its limit, in RMS, for long enough."""

    def __init__(self, limit_mm: float, for_s: float) -> None:
        self.limit_mm, self.for_s = limit_mm, for_s
        self.locked_s: float | None = None  # when it followed its goal a whole window
        self._errors: deque[tuple[float, float]] = deque()  # (t_s, error_mm) since then
        self._first_s = 0.0  # the first error under the limit

    def over_for_s(self, t_s: float, error_mm: float) -> Lag | None:
        """A new measurement's error at ``t_s``; the lag when the RMS over the last
        ``for_s`` (each error held until the next) is over the limit, else None."""
        if self.locked_s is None and not self._errors:
            if error_mm > self.limit_mm:
                return None  # pulling in: the window starts at the first error under the limit
            self._first_s = t_s
        self._errors.append((t_s, error_mm))
        start = t_s - self.for_s
        # keep the error that holds at the window's start
        while len(self._errors) > 1 and self._errors[1][0] <= start:
            self._errors.popleft()
        if start < self._errors[0][0]:
            return None  # not a whole window yet
        square = 0.0
        for (t0, e0), (t1, _) in pairwise(self._errors):
            square += e0 * e0 * (t1 - max(t0, start))
        rms = math.sqrt(square / self.for_s)
        if self.locked_s is None:  # following: a whole window under the limit
            if rms <= self.limit_mm:
                self.locked_s = t_s
                return None
            if t_s - self._first_s < CATCH_UP_WINDOWS * self.for_s:
                return None
        return Lag(rms, self.for_s) if rms > self.limit_mm else None
