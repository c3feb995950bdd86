"""A track that has fallen behind its target: the cell cannot keep up, so it stops.

A conveyor faster than the arm may follow (its speed cap), or a host too loaded to send the
law's twists in time, leaves the TCP behind the moving goal by more and more; a track that
went on would chase the target far off its goal and out of the camera's view. Once a track
has reached its goal (the error under the limit once: the pull-in from wherever it started
is an approach, not a lag), an error over ``[servo] track_lag_mm`` on every new measurement
for ``track_lag_s`` ends it with the arm stopped (``tracking_lag``). Judged on the loop's
own estimate, the error it acts on: frames are the evidence, so a gap between them is the
lost-target clock's to judge, not this one's.
"""

from __future__ import annotations


class LagWatch:
    """Whether a track's error has stayed over its limit for long enough."""

    def __init__(self, limit_mm: float, for_s: float) -> None:
        self.limit_mm, self.for_s = limit_mm, for_s
        self.locked = False  # reached the goal once
        self.over_since_s: float | None = None  # the first measurement of this excursion

    def over_for_s(self, t_s: float, error_mm: float) -> float | None:
        """A new measurement's error at ``t_s``; the seconds it has been over the limit when
        that is ``for_s`` or more (the track must end), else None."""
        if error_mm <= self.limit_mm:
            self.locked, self.over_since_s = True, None
            return None
        if not self.locked:
            return None
        if self.over_since_s is None:
            self.over_since_s = t_s
        over_s = t_s - self.over_since_s
        return over_s if over_s >= self.for_s else None
