"""The live view: the camera frame with detected dots, their ids and the target's axes."""

from __future__ import annotations

from typing import Any

import cv2
import numpy as np
from numpy.typing import NDArray

AXIS_MM = 50.0


def draw(image: NDArray[np.uint8], camera: Any, result: Any, error: str | None,
         frame_age_s: float) -> NDArray[np.uint8]:
    """Colour image with the overlay; ``result`` is an estimator PoseResult or None."""
    out = cv2.cvtColor(image, cv2.COLOR_GRAY2BGR)
    scale = max(1, image.shape[1] // 640)
    if result is not None:
        for blob, idx in zip(result.matched_blobs, result.matched_ids, strict=False):
            c = (round(blob.u), round(blob.v))
            r = max(4, round(np.sqrt(blob.area / np.pi)) + 2)
            cv2.circle(out, c, r, (0, 255, 0), scale)
            cv2.putText(out, str(idx), (c[0] + r + 2, c[1] - r), cv2.FONT_HERSHEY_SIMPLEX,
                        0.5 * scale, (0, 255, 0), scale)
        T = np.asarray(result.T_camera_target, dtype=float)
        pts = np.array([[0, 0, 0], [AXIS_MM, 0, 0], [0, AXIS_MM, 0], [0, 0, AXIS_MM]], float)
        cam_pts = pts @ T[:3, :3].T + T[:3, 3]
        if np.all(cam_pts[:, 2] > 1.0):
            uv = np.round(camera.project(cam_pts)).astype(int)
            o = (int(uv[0, 0]), int(uv[0, 1]))
            for k, colour in zip((1, 2, 3), ((0, 0, 255), (0, 255, 0), (255, 0, 0)),
                                 strict=True):
                cv2.arrowedLine(out, o, (int(uv[k, 0]), int(uv[k, 1])), colour, 2 * scale,
                                tipLength=0.15)
        text = f"rms {result.rms_px:.3f}px  {'AMBIGUOUS  ' if result.ambiguous else ''}" \
               f"age {frame_age_s * 1000:.0f}ms"
        colour = (0, 255, 0)
    else:
        text = f"not located: {error}" if error else f"age {frame_age_s * 1000:.0f}ms"
        colour = (0, 0, 255) if error else (255, 255, 255)
    font_scale = 0.6 * scale
    for k, line in enumerate(wrap(text, out.shape[1] - 20, font_scale, scale)):
        cv2.putText(out, line, (10, (24 + 22 * k) * scale), cv2.FONT_HERSHEY_SIMPLEX,
                    font_scale, colour, scale)
    return np.asarray(out, dtype=np.uint8)


def wrap(text: str, width_px: int, font_scale: float, thickness: int) -> list[str]:
    """``text`` in lines that each fit ``width_px`` in the overlay's font: the whole reason a
    locate failed is shown, never cut at the image's edge (a word longer than a line is split)."""
    def fits(s: str) -> bool:
        (w, _), _ = cv2.getTextSize(s, cv2.FONT_HERSHEY_SIMPLEX, font_scale, thickness)
        return bool(w <= width_px)

    lines: list[str] = []
    line = ""
    for word in text.split():
        while not fits(word):  # split a word wider than the image
            cut = max((n for n in range(1, len(word)) if fits(word[:n])), default=1)
            lines.extend([line] if line else [])
            line = ""
            lines.append(word[:cut])
            word = word[cut:]
        candidate = f"{line} {word}" if line else word
        if fits(candidate):
            line = candidate
        else:
            lines.append(line)
            line = word
    if line:
        lines.append(line)
    return lines


def png(image: NDArray[np.uint8]) -> bytes:
    ok, buf = cv2.imencode(".png", image, [cv2.IMWRITE_PNG_COMPRESSION, 1])
    if not ok:
        raise RuntimeError("PNG encoding failed")
    return bytes(buf)
