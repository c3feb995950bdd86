"""Retention of the hand-eye calibration datasets saved under ``[api] calibration_dir``.

Why: every routine saves its views (about 24 images and their poses) as a folder
``hand-eye-<job id>``; a cell recalibrated weekly fills a small disk in a few years. The newest
``[retention] calibration_datasets_keep`` folders stay, and so does the folder of the
calibration in use, however old: it is the evidence behind every pose the cell reports.
Only folders that name a calibration job are touched; anything else an integrator put there
stays.
"""

from __future__ import annotations

import logging
import shutil
from collections.abc import Iterable
from pathlib import Path

log = logging.getLogger(__name__)
PREFIX = "hand-eye-"


def dataset_folder_name(job_id: str) -> str:
    """The folder a calibration job's views are saved in."""
    return f"{PREFIX}{job_id}"


def prune_datasets(root: Path, keep: int, protected: Iterable[str] = ()) -> int:
    """Delete all but the newest ``keep`` dataset folders (by modification time) under
    ``root``, never one named in ``protected`` -> how many were deleted. ``keep`` 0: none."""
    if keep <= 0 or not root.is_dir():
        return 0
    spared = set(protected)
    folders = []
    for entry in root.iterdir():
        if entry.is_dir() and not entry.is_symlink() and entry.name.startswith(PREFIX):
            try:
                folders.append((entry.stat().st_mtime, entry))
            except OSError:
                continue
    folders.sort(reverse=True)
    deleted = 0
    for _, folder in folders[keep:]:
        if folder.name in spared:
            continue
        try:
            shutil.rmtree(folder)
        except OSError as err:
            log.warning("calibration dataset %s not deleted: %s", folder, err)
            continue
        deleted += 1
    return deleted
