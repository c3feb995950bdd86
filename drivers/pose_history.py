"""A ring buffer of timestamped arm poses, so a camera frame can be paired with the pose the arm
had when the frame was exposed (both stamped with ``time.monotonic()`` on this host)."""

from __future__ import annotations

import bisect
import threading
from collections import deque

import numpy as np
from numpy.typing import NDArray
from scipy.spatial.transform import Rotation, Slerp

# A query this far past the newest sample still gets the newest pose: the arm is sampled every
# few ms, so a frame stamped "just now" must not fail for lack of a newer sample.
NEWEST_TOLERANCE_S = 0.05


class PoseHistory:
    """Thread-safe: one receive thread appends, any thread queries."""

    def __init__(self, max_samples: int = 5000) -> None:
        if max_samples < 2:
            raise ValueError("a pose history needs room for at least 2 samples")
        self._times: deque[float] = deque(maxlen=max_samples)
        self._poses: deque[NDArray[np.float64]] = deque(maxlen=max_samples)
        self._lock = threading.Condition()

    def __len__(self) -> int:
        return len(self._times)

    def add(self, timestamp_s: float, T: NDArray[np.float64]) -> None:
        """Append a sample; samples must arrive in time order (older ones are ignored)."""
        with self._lock:
            if self._times and timestamp_s <= self._times[-1]:
                return
            self._times.append(timestamp_s)
            self._poses.append(np.array(T, dtype=float))
            self._lock.notify_all()

    def span(self) -> tuple[float, float] | None:
        """(oldest, newest) sample time, or None when empty."""
        with self._lock:
            return (self._times[0], self._times[-1]) if self._times else None

    def covers(self, timestamp_s: float, wait_s: float = 0.0) -> bool:
        """Is there a sample at or after ``timestamp_s``? Waits up to ``wait_s`` for one."""
        with self._lock:
            return self._lock.wait_for(
                lambda: bool(self._times) and self._times[-1] >= timestamp_s, timeout=wait_s)

    def at(self, timestamp_s: float, wait_s: float = 0.0) -> NDArray[np.float64]:
        """Pose at ``timestamp_s``: linear in position, slerp in rotation between samples.

        An instant newer than the newest sample waits up to ``wait_s`` for samples to arrive
        (the stream reader may lag a loaded host by a few cycles). LookupError when the instant
        is before the oldest sample or, after that, more than ``NEWEST_TOLERANCE_S`` after the
        newest.
        """
        with self._lock:
            self._lock.wait_for(lambda: bool(self._times) and self._times[-1] >= timestamp_s,
                                timeout=wait_s)
            times = list(self._times)
            poses = list(self._poses)
        if not times or timestamp_s < times[0] or timestamp_s > times[-1] + NEWEST_TOLERANCE_S:
            span = f"[{times[0]:.3f}, {times[-1]:.3f}]" if times else "empty"
            raise LookupError(f"t={timestamp_s:.3f} s is outside the pose history {span}")
        if timestamp_s >= times[-1]:
            return poses[-1].copy()
        i = bisect.bisect_right(times, timestamp_s)
        if i == 0:
            return poses[0].copy()
        t0, t1 = times[i - 1], times[i]
        A, B = poses[i - 1], poses[i]
        w = (timestamp_s - t0) / (t1 - t0)
        out = np.eye(4)
        out[:3, 3] = (1.0 - w) * A[:3, 3] + w * B[:3, 3]
        slerp = Slerp([0.0, 1.0], Rotation.from_matrix(np.stack([A[:3, :3], B[:3, :3]])))
        out[:3, :3] = slerp([w]).as_matrix()[0]
        return out


class ControllerClock:
    """Maps a controller's sample timestamps to this host's ``time.monotonic()``.

    A sample is seen on the host some time after the controller took it: transport plus
    however long the reader took to look (it polls). Stamping the pose history with the
    moment it was seen therefore dates every pose late, by a varying few ms, and a frame
    paired with it gets the pose the arm had a few ms *earlier* (measured on the simulated
    cell: 4-6 ms, 1-2 mm / 0.4-0.7 deg of target error while the arm moves fast). The
    controller's own clock has no such jitter: ``host = controller + offset``, the offset being
    the smallest ``seen - controller`` over the last ``window_s`` (the sample that was
    looked at soonest bounds the delay from above and is the best estimate of it). The
    window lets the offset follow clock drift; a timestamp that goes backwards (a restarted
    controller) starts over.
    """

    def __init__(self, window_s: float = 2.0) -> None:
        self.window_s = window_s
        self._offsets: deque[tuple[float, float]] = deque()  # (seen, offset), offsets rising
        self._last_controller_s: float | None = None

    def host_time(self, controller_s: float, seen_s: float) -> float:
        """The host time the sample was taken (never later than when it was seen)."""
        if self._last_controller_s is not None and controller_s < self._last_controller_s:
            self._offsets.clear()
        self._last_controller_s = controller_s
        offset = seen_s - controller_s
        q = self._offsets
        while q and q[-1][1] >= offset:  # a smaller offset makes larger older ones useless
            q.pop()
        q.append((seen_s, offset))
        while q[0][0] < seen_s - self.window_s:
            q.popleft()
        return min(controller_s + q[0][1], seen_s)
