"""Write the hand-eye result into the cell config's ``[hand_eye]`` table, and nothing else.

Used by ``cell calibrate ... --write-config`` and by the API's apply. The table holds
``T_flange_camera`` as the project's pose object (``position_mm``, ``rotvec_rad``), which is the
schema ``cell.config.schema.HandEyeConfig`` reads.

Only a file that exists and loads as a valid cell config is edited (a mistyped path must not
become a stub config holding only ``[hand_eye]``), and the result must load as one too. A cell
config carries hand-written comments and layout that a TOML round trip would lose, so this edits
the text: it replaces the ``[hand_eye]`` table's lines (or appends the table), then parses the
result and refuses to write unless every other table is unchanged. The old file is kept as a
timestamped backup beside it and the file is replaced atomically, so a failure leaves it as it
was.
"""

from __future__ import annotations

import os
import re
import shutil
import tempfile
import tomllib
from dataclasses import dataclass
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from cell.config.schema import CellConfig, ConfigError, parse_config
from cell.error_codes import ErrorCode
from cell.errors import CellError
from cell.results.calibration import ConfigFileChange, MountTransform
from cell.results.pose import Pose
from estimator.transforms import pose_dict, pose_distance, pose_from_T

TABLE = "hand_eye"
_HEADER = re.compile(r"^\s*\[\[?\s*([A-Za-z0-9_\-.\"' ]+?)\s*\]\]?\s*(#.*)?$")


class ConfigWriteError(CellError):
    """The calibrated mount could not be written to the config file; the file is unchanged."""

    kind = "unavailable"

    def __init__(self, message: str) -> None:
        super().__init__(ErrorCode.config_write_failed, message)


@dataclass(frozen=True)
class ConfigChange:
    """What a write changed: the old and new camera mount, and where the old file is kept."""

    path: Path
    backup: Path
    old_T_flange_camera: NDArray[np.float64]
    new_T_flange_camera: NDArray[np.float64]
    key: MountTransform = "T_flange_camera"  # the [hand_eye] key written

    def distance(self) -> tuple[float, float]:
        return pose_distance(self.new_T_flange_camera, self.old_T_flange_camera)

    def record(self) -> ConfigFileChange:
        """The change as the apply answer and ``cell calibrate --json`` report it."""
        d_mm, d_deg = self.distance()
        return ConfigFileChange(file=str(self.path), backup=str(self.backup),
                                old_T_flange_camera=Pose.from_T(self.old_T_flange_camera),
                                new_T_flange_camera=Pose.from_T(self.new_T_flange_camera),
                                distance_mm=d_mm, distance_deg=d_deg, key=self.key)

    def summary(self) -> str:
        old = pose_dict(self.old_T_flange_camera)
        new = pose_dict(self.new_T_flange_camera)
        d_mm, d_deg = self.distance()

        def fmt(v: list[float], digits: int) -> str:
            return "[" + ", ".join(f"{x:.{digits}f}" for x in v) + "]"

        return (f"[hand_eye] {self.key} in {self.path}:\n"
                f"  position_mm {fmt(old['position_mm'], 3)} -> {fmt(new['position_mm'], 3)}\n"
                f"  rotvec_rad  {fmt(old['rotvec_rad'], 5)} -> {fmt(new['rotvec_rad'], 5)}\n"
                f"  moved {d_mm:.3f} mm / {d_deg:.4f} deg; the old file is kept as {self.backup}")


def hand_eye_table(T_flange_camera: NDArray[np.float64], comment: str = "",
                   key: str = "T_flange_camera") -> str:
    """The ``[hand_eye]`` table; ``key`` is ``T_base_camera`` for a fixed camera."""
    position_mm, rotvec_rad = pose_from_T(T_flange_camera)
    lines = [f"[{TABLE}]"]
    if comment:
        lines += [f"# {line}" for line in comment.splitlines()]
    lines.append(
        f"{key} = {{ position_mm = [" + ", ".join(repr(v) for v in position_mm)
        + "], rotvec_rad = [" + ", ".join(repr(v) for v in rotvec_rad) + "] }"
    )
    return "\n".join(lines) + "\n"


def _mount_T(config: CellConfig) -> NDArray[np.float64]:
    """The calibrated camera mount the config states (flange or base frame)."""
    if config.fixed_camera and config.hand_eye.T_base_camera is not None:
        return config.hand_eye.T_base_camera.T()
    return config.hand_eye.T_flange_camera.T()


def write_hand_eye(
    path: str | Path, T_flange_camera: NDArray[np.float64], comment: str = ""
) -> ConfigChange:
    """Update ``[hand_eye] T_flange_camera`` in the cell config at ``path``; returns the change.

    Refused (ConfigWriteError, nothing written) unless the file exists, loads as a valid cell
    config, and still does with only its ``[hand_eye]`` table changed.
    """
    p = Path(path)
    if not p.is_file():
        raise ConfigWriteError(f"{p} does not exist: the result is written only into an "
                               "existing cell config (check the path)")
    try:
        old_text = p.read_text()
        old = tomllib.loads(old_text)
    except (OSError, UnicodeDecodeError, tomllib.TOMLDecodeError) as err:
        raise ConfigWriteError(f"cannot update {p}: it is not readable TOML ({err})") from err
    try:
        old_config = parse_config(old, str(p))
        old_T = _mount_T(old_config)
    except ConfigError as err:
        raise ConfigWriteError(f"cannot update {p}: it is not a valid cell config ({err}); fix "
                               "it first (`cell config check FILE`)") from err
    key: MountTransform = "T_base_camera" if old_config.fixed_camera else "T_flange_camera"
    table = hand_eye_table(T_flange_camera, comment, key)
    new_text = _replace_table(old_text, table)
    try:
        new = tomllib.loads(new_text)
    except tomllib.TOMLDecodeError as err:
        raise ConfigWriteError(f"cannot update {p} safely: {err}; edit [{TABLE}] by hand") from err
    if _without(new, TABLE) != _without(old, TABLE) or TABLE not in new:
        raise ConfigWriteError(
            f"cannot update {p} safely: [{TABLE}] is written in a form this tool does not edit "
            "(inline or dotted keys); move it into its own [hand_eye] table"
        )
    try:
        written = _mount_T(parse_config(new, str(p)))
    except ConfigError as err:
        raise ConfigWriteError(f"the updated {p} would not be a valid cell config: {err}") \
            from err
    backup = _backup(p)
    _atomic_write(p, new_text)
    return ConfigChange(p, backup, old_T, written, key)


def _backup(path: Path) -> Path:
    """Copy ``path`` to ``NAME.YYYYmmddTHHMMSSZ.bak`` beside it (never over an older backup)."""
    stamp = datetime.now(UTC).strftime("%Y%m%dT%H%M%SZ")
    backup = path.with_name(f"{path.name}.{stamp}.bak")
    k = 1
    while backup.exists():
        backup = path.with_name(f"{path.name}.{stamp}-{k}.bak")
        k += 1
    try:
        shutil.copy2(path, backup)
    except OSError as err:
        raise ConfigWriteError(f"cannot keep a backup of {path} as {backup}: {err}; nothing "
                               "was written") from err
    return backup


def _without(data: dict[str, Any], key: str) -> dict[str, Any]:
    return {k: v for k, v in data.items() if k != key}


def _replace_table(text: str, table: str) -> str:
    lines = text.splitlines(keepends=True)
    start = end = None
    for i, line in enumerate(lines):
        m = _HEADER.match(line)
        if not m:
            continue
        name = m.group(1).strip().strip("\"'")
        if start is None and name == TABLE and not line.lstrip().startswith("[["):
            start = i
        elif start is not None and end is None and not name.startswith(TABLE + "."):
            end = i
    if start is None:
        sep = "" if not text or text.endswith("\n\n") else ("\n" if text.endswith("\n") else "\n\n")
        return text + sep + table
    end = len(lines) if end is None else end
    # keep blank lines and comments that precede the next table with that table
    while end > start + 1 and lines[end - 1].strip() in ("", *_comment(lines[end - 1])):
        end -= 1
    tail = "".join(lines[end:])
    gap = "\n" if tail and not tail.startswith("\n") else ""
    return "".join(lines[:start]) + table + gap + tail


def _comment(line: str) -> tuple[str, ...]:
    stripped = line.strip()
    return (stripped,) if stripped.startswith("#") else ()


def _atomic_write(path: Path, text: str) -> None:
    directory = path.parent if str(path.parent) else Path(".")
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", dir=directory)
    try:
        with os.fdopen(fd, "w") as f:
            f.write(text)
        if path.exists():
            os.chmod(tmp, path.stat().st_mode & 0o777)
        os.replace(tmp, path)
    except OSError as err:
        Path(tmp).unlink(missing_ok=True)
        raise ConfigWriteError(f"cannot write {path}: {err}") from err
