"""When a tracked target counts as lost: judged on the camera's clock, frame by frame.

The frame pipeline is serial: it takes the newest frame, estimates it (tens of ms, far more on
a loaded host), and only then looks at the next newest one, skipping those exposed meanwhile.
So the exposures of consecutive poses lie a whole pipeline period apart (its latency plus the
wait for a frame), and on a host clock the target looks unseen for that long while every frame
still shows it. That period is not the target's absence.

The target is lost when frames *examined* after the last pose, exposed ``lost_after_s`` or
more after it, did not show it: ``newest examined exposure - last pose's exposure``. A covered
lens is seen that way as soon as the first frame exposed ``lost_after_s`` after the cover has
been examined (a frame without dots fails fast). A pipeline that examines nothing at all (a
stalled camera, a hung estimator) has no camera time to judge by; it counts as lost once the
host clock is ``stall_after_s`` past the newest examined exposure. Never from before
``floor_s`` (the loop's start: the frames before it are not this run's).
"""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class Silence:
    camera_s: float  # examined frames' exposures since the last pose (camera time)
    stalled_s: float  # host time since the newest examined frame's exposure
    lost: bool

    def describe(self, lost_after_s: float, stall_after_s: float,
                 unseen: str = "pose did not show the target") -> str:
        """Why the target counts as lost, for the job's error message."""
        if self.camera_s > lost_after_s:
            return (f"frames exposed for {self.camera_s * 1000:.0f} ms after the last {unseen} "
                    f"(limit {lost_after_s * 1000:.0f} ms of camera time)")
        return (f"no frame examined for {self.stalled_s * 1000:.0f} ms (limit "
                f"{stall_after_s * 1000:.0f} ms: the camera or the estimator stalled)")


class LossClock:
    """Not thread-safe: the servo loop calls it under its own lock."""

    def __init__(self, lost_after_s: float, stall_after_s: float, floor_s: float,
                 last_pose_exposure_s: float | None = None) -> None:
        if lost_after_s <= 0 or stall_after_s < lost_after_s:
            raise ValueError("need 0 < lost_after_s <= stall_after_s")
        self.lost_after_s, self.stall_after_s = lost_after_s, stall_after_s
        self.floor_s = floor_s
        start = floor_s if last_pose_exposure_s is None else max(last_pose_exposure_s, floor_s)
        self.last_pose_exposure_s = start
        self.newest_examined_s = start

    def restart(self, floor_s: float) -> None:
        """The loop starts now: nothing exposed before ``floor_s`` counts either way."""
        self.floor_s = floor_s
        self.last_pose_exposure_s = max(self.last_pose_exposure_s, floor_s)
        self.newest_examined_s = max(self.newest_examined_s, floor_s)

    def pose(self, exposure_s: float) -> None:
        """A frame exposed at ``exposure_s`` showed the target and its pose was used."""
        self.last_pose_exposure_s = max(self.last_pose_exposure_s, exposure_s)
        self.examined(exposure_s)

    def examined(self, exposure_s: float) -> None:
        """A frame exposed at ``exposure_s`` was looked at (with or without the target)."""
        self.newest_examined_s = max(self.newest_examined_s, exposure_s)

    def silence(self, now_s: float) -> Silence:
        camera = max(0.0, self.newest_examined_s - self.last_pose_exposure_s)
        stalled = now_s - self.newest_examined_s
        return Silence(camera, stalled, camera > self.lost_after_s
                       or stalled > self.stall_after_s)
