"""What the cell's modules share: the config, the guarded arm, the slot, the logs.

Built once by :class:`cell.service.Cell`; each module (approach, jog, recovery, links,
status, calibration, teach) gets this instead of reaching into the facade or the devices.
Only ``arm`` moves anything, and it is the guarded one.
"""

from __future__ import annotations

import threading
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from cell.config.schema import CellConfig
from cell.devices.hardware import Hardware
from cell.jobs.audit import Auditor
from cell.jobs.events import EventBus
from cell.jobs.runner import JobRunner
from cell.jobs.store import JobStore
from cell.motion.guard import GuardedArm, MotionSlot
from cell.stats import CellStats
from cell.vision.frames import CellFrames
from cell.vision.locate import Locator
from drivers.camera import Camera
from drivers.gripper import Gripper
from estimator import Target


@dataclass
class CellCore:
    config: CellConfig
    hw: Hardware
    arm: GuardedArm
    slot: MotionSlot
    jobs: JobStore
    events: EventBus
    audit: Auditor
    runner: JobRunner
    locator: Locator
    stats: CellStats
    frames: CellFrames
    target: Target
    lock: threading.RLock = field(default_factory=threading.RLock)

    @property
    def camera(self) -> Camera:
        return self.hw.camera

    @property
    def gripper(self) -> Gripper | None:
        return self.hw.gripper

    @property
    def target_centre_mm(self) -> NDArray[np.float64]:
        return np.asarray(self.target.points_mm, dtype=float).mean(axis=0)
