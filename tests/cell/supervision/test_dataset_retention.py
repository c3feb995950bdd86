"""Retention of the hand-eye routines' saved datasets: the newest N folders stay, and the
calibration in use stays however old; nothing else under the calibration folder is touched."""

from __future__ import annotations

import os
from pathlib import Path
from types import SimpleNamespace
from typing import Any

from cell.calibration.service import CalibrationService
from cell.config.schema import RetentionConfig
from cell.jobs.store import JobStore
from cell.supervision.dataset_retention import dataset_folder_name, prune_datasets
from cell.supervision.retention import Retention


def _datasets(root: Path, n: int) -> list[str]:
    """``n`` dataset folders, the first the oldest (one image each)."""
    names = []
    for k in range(n):
        folder = root / dataset_folder_name(f"job{k:02d}")
        folder.mkdir(parents=True)
        (folder / "view-00.png").write_bytes(b"\x89PNG" + bytes(1000))
        os.utime(folder, (1_000_000.0 + k, 1_000_000.0 + k))
        names.append(folder.name)
    return names


def test_the_newest_stay_the_one_in_use_stays_and_other_folders_are_untouched(
        tmp_path: Path) -> None:
    names = _datasets(tmp_path, 6)
    (tmp_path / "notes").mkdir()  # an integrator's own folder
    (tmp_path / "hand-eye-readme.txt").write_text("a file, not a dataset")
    assert prune_datasets(tmp_path, 2, protected={names[0]}) == 3
    left = sorted(p.name for p in tmp_path.iterdir())
    assert left == sorted([names[0], names[4], names[5], "notes", "hand-eye-readme.txt"])
    assert prune_datasets(tmp_path, 2, protected={names[0]}) == 0  # nothing more to do


def test_keep_zero_keeps_every_dataset_and_a_missing_folder_is_no_error(tmp_path: Path) -> None:
    _datasets(tmp_path, 3)
    assert prune_datasets(tmp_path, 0) == 0 and len(list(tmp_path.iterdir())) == 3
    assert prune_datasets(tmp_path / "absent", 1) == 0


def test_the_calibration_in_use_comes_from_the_audit_log_and_survives_a_retention_pass(
        tmp_path: Path) -> None:
    store = JobStore(tmp_path / "jobs.db")
    root = tmp_path / "calibration"
    names = _datasets(root, 5)
    calibration: Any = CalibrationService.__new__(CalibrationService)
    calibration.core = SimpleNamespace(jobs=store)
    assert calibration.datasets_in_use() == set()  # the config file's calibration
    store.audit("operator", "apply_calibration", {"job_id": "job01", "running": True},
                "ok", "", "job01")
    store.audit("operator", "apply_calibration", {"job_id": "job03", "running": True},
                "refused", "the arm moves", "job03")  # refused: not in use
    assert calibration.datasets_in_use() == {names[1]}
    retention = Retention(RetentionConfig(calibration_datasets_keep=2), store,
                          lambda before_s, limit: 0, datasets=root,
                          datasets_in_use=calibration.datasets_in_use)
    done = retention.run_once()
    assert done.datasets == 2 and not done.errors
    assert sorted(p.name for p in root.iterdir()) == sorted([names[1], names[3], names[4]])
    store.close()
