"""The one guarded path to the arm: every motion passes here, and a refusal moves nothing.

- :mod:`~cell.motion.guard`: the motion slot (one motion at a time) and the guarded arm;
- :mod:`~cell.motion.limits`: the envelope, speed, tilt and distance checks run before anything
  is commanded;
- :mod:`~cell.motion.twist`: where a TCP moving at a commanded twist is a moment later.
"""

from cell.motion.guard import GuardedArm, Motion, MotionSlot

__all__ = ["GuardedArm", "Motion", "MotionSlot"]
