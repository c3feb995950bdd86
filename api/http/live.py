"""The live view: one overlay drawing and one JPEG encode per camera frame, shared by viewers.

Why: encoding the overlay frame per request made every open page cost a full PNG encode
(~700 KB, ~45 ms of CPU) and loaded the host enough to disturb approaches. Here the newest
encoded frame is kept; a viewer asking again within ``min_period_s`` (or before the camera has
a newer frame) gets the same bytes, so five viewers cost what one does. Nothing is produced
while nobody looks.
"""

from __future__ import annotations

import threading
import time
from dataclasses import dataclass

import cv2
import numpy as np
from numpy.typing import NDArray

from api.http import overlay
from cell.service import Cell

JPEG_QUALITY = 80
LIVE_MAX_FPS = 8.0  # the page shows at most this many frames per second per camera


@dataclass(frozen=True)
class LiveFrame:
    jpeg: bytes
    sequence: int  # the camera frame's sequence number
    timestamp_s: float  # its capture time (time.monotonic())
    overlay: bool
    produced_s: float  # when it was encoded (time.monotonic())
    # What the overlay says (None without one): located or not, and the estimate's quality or
    # why not. The page's quality row shows these, so it never disagrees with the image.
    located: bool | None = None
    rms_px: float | None = None
    ambiguous: bool | None = None
    error: str | None = None

    def headers(self) -> dict[str, str]:
        """``X-Located``, ``X-Locate-Rms-Px``, ``X-Locate-Ambiguous``, ``X-Locate-Error``."""
        if self.located is None:
            return {}
        if not self.located:
            words = (self.error or "").encode("ascii", "replace").decode()
            return {"X-Located": "false", "X-Locate-Error": " ".join(words.split())[:200]}
        out = {"X-Located": "true", "X-Locate-Ambiguous": str(bool(self.ambiguous)).lower()}
        if self.rms_px is not None:
            out["X-Locate-Rms-Px"] = f"{self.rms_px:.4f}"
        return out


def encode_jpeg(image: NDArray[np.uint8], quality: int = JPEG_QUALITY) -> bytes:
    ok, buf = cv2.imencode(".jpg", image, [cv2.IMWRITE_JPEG_QUALITY, quality])
    if not ok:
        raise RuntimeError("JPEG encoding failed")
    return bytes(buf)


class LiveView:
    """Thread-safe cache of the newest encoded frame, one with and one without the overlay."""

    def __init__(self, cell: Cell, max_fps: float = LIVE_MAX_FPS) -> None:
        self.cell = cell
        self.min_period_s = 1.0 / max(1e-3, min(max_fps, cell.config.camera.fps))
        self._lock = threading.Lock()
        self._latest: dict[bool, LiveFrame] = {}
        self.encodes = 0  # for tests and the benchmark: how many frames were really encoded

    def frame(self, with_overlay: bool = True) -> LiveFrame:
        """The newest live frame (UnavailableError ``camera_lost`` when the camera is)."""
        with self._lock:  # viewers queue here while one of them produces the frame
            cached = self._latest.get(with_overlay)
            now = time.monotonic()
            if cached is not None and now - cached.produced_s < self.min_period_s:
                return cached
            frame, result, error = self.cell.preview(with_overlay)
            if cached is not None and cached.sequence == frame.sequence:
                return cached
            if with_overlay:
                age_s = max(0.0, time.monotonic() - frame.timestamp_s)
                image = overlay.draw(frame.image, frame.camera, result, error, age_s)
            else:
                image = frame.image
            live = LiveFrame(
                encode_jpeg(image), frame.sequence, frame.timestamp_s, with_overlay,
                time.monotonic(),
                located=(result is not None) if with_overlay else None,
                rms_px=float(result.rms_px) if result is not None else None,
                ambiguous=bool(result.ambiguous) if result is not None else None,
                error=error if with_overlay else None)
            self.encodes += 1
            self._latest[with_overlay] = live
            return live
