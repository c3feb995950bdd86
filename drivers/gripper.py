"""The gripper interface (adapters: drivers.robotiq; fake: fakes.gripper)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol, runtime_checkable


@dataclass(frozen=True)
class GripperStatus:
    """What the gripper reports; ``fault`` is None or a short text naming the fault."""

    activated: bool
    position_mm: float  # finger opening
    object_detected: bool
    moving: bool
    fault: str | None = None

    def as_dict(self) -> dict[str, object]:
        return {
            "activated": self.activated, "position_mm": self.position_mm,
            "object_detected": self.object_detected, "moving": self.moving, "fault": self.fault,
        }


@runtime_checkable
class Gripper(Protocol):
    def connect(self) -> None: ...
    def disconnect(self) -> None: ...
    def activate(self) -> GripperStatus: ...
    def open(self, wait: bool = True) -> GripperStatus: ...
    def close(self, wait: bool = True) -> GripperStatus: ...
    def move(
        self, position_mm: float, speed_pct: float = 100.0, force_pct: float = 50.0,
        wait: bool = True,
    ) -> GripperStatus: ...
    def wait_for_motion(self, timeout_s: float | None = None) -> GripperStatus:
        """Until the fingers of the last move (sent with ``wait=False``) stopped: at the
        request, on an object, or halted."""

    def stop(self) -> GripperStatus:
        """Halt the fingers where they are; a grip already made keeps its object."""

    def status(self) -> GripperStatus: ...
