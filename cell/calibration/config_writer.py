"""Write the hand-eye result into the cell config's ``[hand_eye]`` table, and nothing else.

The table holds ``T_flange_camera`` as the project's pose object (``position_mm``,
``rotvec_rad``), which is the schema ``cell.config.HandEyeConfig`` reads.

A cell config carries hand-written comments and layout that a TOML round trip would lose, so
this edits the text: it replaces the ``[hand_eye]`` table's lines (or appends the table), then
parses the result with tomllib and refuses to write unless every other table is unchanged.
The file is replaced atomically, so a failure leaves the old file as it was.
"""

from __future__ import annotations

import os
import re
import tempfile
import tomllib
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from cell.config import ConfigError, parse_config
from estimator.transforms import pose_from_T

TABLE = "hand_eye"
_HEADER = re.compile(r"^\s*\[\[?\s*([A-Za-z0-9_\-.\"' ]+?)\s*\]\]?\s*(#.*)?$")


class ConfigWriteError(Exception):
    code = "config_write_failed"


def hand_eye_table(T_flange_camera: NDArray[np.float64], comment: str = "") -> str:
    position_mm, rotvec_rad = pose_from_T(T_flange_camera)
    lines = [f"[{TABLE}]"]
    if comment:
        lines += [f"# {line}" for line in comment.splitlines()]
    lines.append(
        "T_flange_camera = { position_mm = [" + ", ".join(repr(v) for v in position_mm)
        + "], rotvec_rad = [" + ", ".join(repr(v) for v in rotvec_rad) + "] }"
    )
    return "\n".join(lines) + "\n"


def write_hand_eye(
    path: str | Path, T_flange_camera: NDArray[np.float64], comment: str = ""
) -> None:
    """Create or update ``[hand_eye] T_flange_camera`` in the TOML file at ``path``.

    A file that was a valid cell config must stay one; a partial file (e.g. a fragment that
    is merged elsewhere) only has to stay valid TOML with its other tables unchanged.
    """
    p = Path(path)
    old_text = ""
    if p.exists():
        try:
            old_text = p.read_text()
            old = tomllib.loads(old_text)
        except (OSError, UnicodeDecodeError, tomllib.TOMLDecodeError) as err:
            raise ConfigWriteError(f"cannot update {p}: it is not readable TOML ({err})") from err
    else:
        old = {}
    table = hand_eye_table(T_flange_camera, comment)
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
    if old and _valid_cell_config(old):
        try:
            parse_config(new, str(p))
        except ConfigError as err:
            raise ConfigWriteError(f"the updated {p} would not be a valid cell config: {err}") \
                from err
    _atomic_write(p, new_text)


def _valid_cell_config(data: dict[str, Any]) -> bool:
    try:
        parse_config(data)
    except ConfigError:
        return False
    return True


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
