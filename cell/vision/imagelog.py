"""Optional bounded ring on disk of frames whose locate failed, with what was detected.

Why: a failed locate in production is usually lighting, dirt or a moved target; the frame
plus the detections is what a person needs to tell which. The ring keeps the newest
``max_entries`` so the disk never fills.
"""

from __future__ import annotations

import json
import re
import threading
import time
from pathlib import Path
from typing import Any

import cv2
import numpy as np
from numpy.typing import NDArray


class ImageLog:
    """``<dir>/<stamp>.png`` + ``<stamp>.json`` pairs, oldest deleted beyond ``max_entries``."""

    def __init__(self, directory: str | Path, max_entries: int = 50) -> None:
        self.directory = Path(directory)
        self.directory.mkdir(parents=True, exist_ok=True)
        self.max_entries = max_entries
        self._lock = threading.Lock()
        self._counter = 0

    def save(self, image: NDArray[np.uint8], info: dict[str, Any]) -> Path:
        with self._lock:
            self._counter += 1
            stem = f"{time.strftime('%Y%m%dT%H%M%S')}_{time.time_ns() % 10**9:09d}_{self._counter}"
            png = self.directory / f"{stem}.png"
            cv2.imwrite(str(png), image)
            (self.directory / f"{stem}.json").write_text(json.dumps(info, default=str, indent=1))
            self._trim()
            return png

    def entries(self) -> list[Path]:
        return sorted(self.directory.glob("*.png"), key=lambda p: p.stat().st_mtime_ns)

    def _trim(self) -> None:
        pngs = self.entries()
        for old in pngs[: max(0, len(pngs) - self.max_entries)]:
            old.unlink(missing_ok=True)
            old.with_suffix(".json").unlink(missing_ok=True)

    def prune(self, saved_before_s: float, max_bytes: int) -> int:
        """Delete the entries saved before UNIX time ``saved_before_s`` and then the oldest
        until the rest take at most ``max_bytes``; how many went."""
        with self._lock:
            sized = []
            for png in self.entries():
                try:
                    st = png.stat()
                    info = png.with_suffix(".json")
                    sized.append((png, st.st_mtime, st.st_size
                                  + (info.stat().st_size if info.exists() else 0)))
                except OSError:
                    continue
            total, gone = sum(n for _, _, n in sized), 0
            for png, saved_s, n in sized:
                if saved_s >= saved_before_s and total <= max_bytes:
                    break
                png.unlink(missing_ok=True)
                png.with_suffix(".json").unlink(missing_ok=True)
                total, gone = total - n, gone + 1
            return gone

    def page(self, offset: int = 0, limit: int = 20) -> tuple[list[dict[str, Any]], int]:
        """Entries newest first with what was recorded about each, and how many there are."""
        pngs = self.entries()[::-1]
        out = []
        for png in pngs[offset:offset + limit]:
            try:
                info = json.loads(png.with_suffix(".json").read_text())
            except (OSError, ValueError):
                info = {}
            try:
                saved_at = png.stat().st_mtime
            except OSError:
                continue  # trimmed meanwhile
            out.append({"name": png.stem, "code": info.get("code"),
                        "message": info.get("message"), "saved_at": saved_at, "info": info})
        return out, len(pngs)

    def image_path(self, name: str) -> Path | None:
        """The PNG of entry ``name``, or None; names are checked, never joined blindly."""
        if not _NAME.fullmatch(name):
            return None
        path = self.directory / f"{name}.png"
        return path if path.is_file() else None


_NAME = re.compile(r"[0-9T]{15}_[0-9]{9}_[0-9]+")
