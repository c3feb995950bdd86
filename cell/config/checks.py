"""Commissioning checks on a cell config, beyond its schema: the mistakes an integrator makes.

A value can be of the right type and inside its hard bounds and still be almost surely wrong: a
tool offset typed in metres, a speed in m/s, joint angles in radians, a timeout in milliseconds.
Each check names the key and the likely mistake; it is an error unless that key is listed in
``[commissioning] accept = [...]``, so a deliberate unusual value is a recorded decision rather
than a silent one. Real hardware also needs the tables whose defaults only suit the simulated
cell (``[limits]``, ``[tool]``, ``[hand_eye]``).

The checks read the raw TOML data (not the validated model), so ``cell config check`` lists them
together with every schema error in one pass; values of the wrong type are left to the schema.
"""

from __future__ import annotations

import difflib
import math
from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from typing import Any

from cell.config.devices import DEVICE_TABLES

# Tables a config with real hardware must state: their defaults fit only the simulated cell.
REAL_REQUIRED_TABLES: dict[str, str] = {
    "limits": "the default workspace box reaches 100 mm below the robot base",
    "tool": "the default tool is the bare flange (identity T_flange_tcp)",
    "hand_eye": "the default camera mount is the flange origin (identity T_flange_camera)",
}

POSITION_KEYS = ("tool.T_flange_tcp.position_mm", "hand_eye.T_flange_camera.position_mm",
                 "hand_eye.T_base_camera.position_mm")
SPEED_KEYS = ("approach.speed_mm_s", "limits.max_speed_mm_s", "limits.max_jog_speed_mm_s")
ACCEL_KEYS = ("approach.accel_mm_s2", "limits.max_accel_mm_s2")
JOINT_KEYS = ("robot.home_joints_deg",)
WORKSPACE_KEYS = ("limits.workspace_min_mm", "limits.workspace_max_mm")
TIME_KEYS = (
    "robot.connect_timeout_s", "robot.call_timeout_s", "robot.watchdog_s",
    "robot.stale_after_s", "gripper.timeout_s", "gripper.motion_timeout_s",
    "gripper.activation_timeout_s", "limits.max_pose_age_s", "approach.settle_s",
)
STATE_DIR_KEY = "api.state_dir"
CHECKED_KEYS: tuple[str, ...] = (
    *POSITION_KEYS, *SPEED_KEYS, *ACCEL_KEYS, *JOINT_KEYS, *WORKSPACE_KEYS, *TIME_KEYS,
    STATE_DIR_KEY,
)

MIN_OFFSET_MM = 5.0
MIN_SPEED_MM_S = 1.0
MAX_RADIANS = 6.3  # a full turn is 6.283 rad: every joint inside +-6.3 reads as radians
MAX_TIME_S = 60.0


@dataclass(frozen=True)
class Problem:
    """One thing wrong with a config: the dotted key and what is wrong with it."""

    key: str
    message: str

    def as_dict(self) -> dict[str, str]:
        return {"key": self.key, "message": self.message}

    def __str__(self) -> str:
        return f"{self.key}: {self.message}"


def closest(name: str, valid: Sequence[str]) -> str | None:
    """The valid name most like ``name`` (a typo, a wrong unit suffix), or None."""
    hits = difflib.get_close_matches(name, list(valid), n=1, cutoff=0.6)
    if hits:
        return hits[0]
    lowered = {v.lower(): v for v in valid}
    hits = difflib.get_close_matches(name.lower(), list(lowered), n=1, cutoff=0.5)
    return lowered[hits[0]] if hits else None


@dataclass(frozen=True)
class _RawStandIns:
    """The raw ``[sim]`` table's stand-ins, as :meth:`DeviceConfig.is_hardware` reads them."""

    ur_controller: bool


def has_real_device(data: dict[str, Any]) -> bool:
    """True when a device table of the raw config names a kind that is real hardware: the
    device classes' own rule (:meth:`cell.config.devices.DeviceConfig.is_hardware`), read off
    each table's ``kind`` before the schema has validated the rest."""
    sim = _RawStandIns(ur_controller=_table(data, "sim").get("ur_controller") is True)
    for table in DEVICE_TABLES:
        kind = table.config_class(_table(data, table.name))
        if kind is not None and kind.is_hardware(sim):
            return True
    return False


def check(data: dict[str, Any]) -> list[Problem]:
    """Every commissioning problem of the raw config ``data`` not accepted by
    ``[commissioning] accept``."""
    accept, problems = _accepted(data)
    real = has_real_device(data)
    if real:
        for table, why in REAL_REQUIRED_TABLES.items():
            if table not in data:
                problems.append(Problem(table, f"required with real hardware ({why}); state "
                                        f"[{table}] explicitly"))
    for key, message in _plausibility(data, real):
        if key not in accept:
            problems.append(Problem(key, f"{message} (if this is intended, list \"{key}\" in "
                                    "[commissioning] accept)"))
    return problems


def _accepted(data: dict[str, Any]) -> tuple[set[str], list[Problem]]:
    raw = _table(data, "commissioning").get("accept", [])
    if not isinstance(raw, list):
        return set(), []  # the schema reports the type
    accept, problems = set(), []
    for k, key in enumerate(raw):
        if not isinstance(key, str):
            continue
        if key in CHECKED_KEYS:
            accept.add(key)
            continue
        hint = closest(key, CHECKED_KEYS)
        problems.append(Problem(
            f"commissioning.accept.{k}",
            f"{key!r} is not a checked key" + (f"; did you mean {hint!r}?" if hint else
                                                f"; checked keys: {', '.join(CHECKED_KEYS)}")))
    return accept, problems


def _plausibility(data: dict[str, Any], real: bool) -> Iterator[tuple[str, str]]:
    for key in POSITION_KEYS:
        v = _vector(data, key)
        if v is not None and 0.0 < math.hypot(*v) < MIN_OFFSET_MM:
            yield key, (f"offset of {math.hypot(*v):.3g} mm is under {MIN_OFFSET_MM:g} mm: is it "
                        "in metres? write millimetres (0.15 m = 150.0)")
    for key in SPEED_KEYS:
        x = _number(data, key)
        if x is not None and 0.0 < x < MIN_SPEED_MM_S:
            yield key, f"{x:g} mm/s is under 1 mm/s: is it in m/s? write mm/s (0.15 m/s = 150.0)"
    for key in ACCEL_KEYS:
        x = _number(data, key)
        if x is not None and 0.0 < x < 1.0:
            yield key, f"{x:g} mm/s^2 is under 1 mm/s^2: is it in m/s^2? write mm/s^2"
    for key in JOINT_KEYS:
        v = _vector(data, key)
        if v is not None and max(abs(x) for x in v) > 0 and all(abs(x) <= MAX_RADIANS for x in v):
            yield key, (f"every joint value is within +-{MAX_RADIANS}: are they radians? write "
                        "degrees (-1.5708 rad = -90.0)")
    box = [_vector(data, key) for key in WORKSPACE_KEYS]
    if all(v is not None for v in box) and all(abs(x) < MIN_OFFSET_MM for v in box
                                               for x in v or ()):
        yield WORKSPACE_KEYS[0], ("the workspace box is under 5 mm on every side: is it in "
                                  "metres? write millimetres")
    for key in TIME_KEYS:
        x = _number(data, key)
        if x is not None and x > MAX_TIME_S:
            yield key, f"{x:g} s is over {MAX_TIME_S:g} s: is it in milliseconds? write seconds"
    state_dir = _table(data, "api").get("state_dir", "")
    if real and state_dir == "":
        yield STATE_DIR_KEY, ("empty with real hardware: the job database, calibrations and "
                              "taught poses would land in the working directory; set an "
                              "absolute folder such as /var/lib/ur-vision-cell")


def _table(data: dict[str, Any], name: str) -> dict[str, Any]:
    t = data.get(name)
    return t if isinstance(t, dict) else {}


def _value(data: dict[str, Any], key: str) -> Any:
    node: Any = data
    for part in key.split("."):
        if not isinstance(node, dict) or part not in node:
            return None
        node = node[part]
    return node


def _is_number(x: Any) -> bool:
    return isinstance(x, int | float) and not isinstance(x, bool) and math.isfinite(x)


def _number(data: dict[str, Any], key: str) -> float | None:
    x = _value(data, key)
    return float(x) if _is_number(x) else None


def _vector(data: dict[str, Any], key: str) -> list[float] | None:
    v = _value(data, key)
    if isinstance(v, list | tuple) and v and all(_is_number(x) for x in v):
        return [float(x) for x in v]
    return None
