"""The rules an approach's own numbers obey, wherever they come from.

One rule for every door: an ``/approach`` body, a recipe's target when it is saved, a recipe
approach's override, the PLC interfaces. A standoff is a finite number in
``[0, MAX_STANDOFF_MM]`` (``invalid_standoff``); a speed is inside the configured
``[limits] min_speed_mm_s .. max_speed_mm_s`` (``speed_limit``, the guard's own check). Each
refusal names the field it is about.
"""

from __future__ import annotations

import math
from typing import Any

from cell.config.schema import LimitsConfig
from cell.error_codes import ErrorCode
from cell.errors import LimitError
from cell.motion.limits import SafetyGuard

MAX_STANDOFF_MM = 500.0  # farther than this the camera cannot resolve the dots anyway


def check_standoff(standoff_mm: Any, field: str = "standoff_mm") -> float:
    """The standoff as a float, or ``invalid_standoff`` naming ``field``."""
    if isinstance(standoff_mm, bool) or not isinstance(standoff_mm, int | float) \
            or not math.isfinite(standoff_mm) or not 0 <= standoff_mm <= MAX_STANDOFF_MM:
        raise LimitError(ErrorCode.invalid_standoff,
                         f"{field} must be a number in [0, {MAX_STANDOFF_MM:g}] mm, "
                         f"got {standoff_mm!r}")
    return float(standoff_mm)


def check_speed(limits: LimitsConfig, speed_mm_s: Any, field: str = "speed_mm_s") -> float:
    """The speed as a float, or ``speed_limit`` naming ``field`` (the guard's bounds)."""
    if isinstance(speed_mm_s, bool) or not isinstance(speed_mm_s, int | float):
        raise LimitError(ErrorCode.speed_limit, f"{field} must be a number, got {speed_mm_s!r}")
    try:
        SafetyGuard(limits).check_speed(float(speed_mm_s), limits.max_accel_mm_s2)
    except LimitError as err:
        raise LimitError(err.code, f"{field}: {err.message}") from err
    return float(speed_mm_s)
