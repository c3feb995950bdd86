"""Helpers shared by subcommands: JSON output, typed errors -> exit code 2, progress bars,
quiet image reading."""

from __future__ import annotations

import json
import sys
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    import numpy as np
    from numpy.typing import NDArray

EXIT_OK, EXIT_NO, EXIT_ERROR = 0, 1, 2
Progress = Callable[[str, int, int], None]  # (stage, done, total)


def print_json(obj: Any) -> None:
    json.dump(obj, sys.stdout, indent=2)
    sys.stdout.write("\n")


def fail(code: str, message: str, as_json: bool) -> int:
    """Report a failure the documented way and return exit status 2."""
    if as_json:
        print_json({"error": {"code": code, "message": message}})
    else:
        print(f"error ({code}): {message}", file=sys.stderr)
    return 2


def read_grey(path: str | Path) -> NDArray[np.uint8] | str:
    """The image at ``path`` as 8-bit grey, or why it cannot be read (OpenCV's own loader
    warnings stay off stderr: the returned reason says it in words)."""
    import cv2
    import numpy as np

    p = Path(path)
    if not p.is_file():
        return f"cannot read {p}: no such file"
    cv2.utils.logging.setLogLevel(cv2.utils.logging.LOG_LEVEL_ERROR)
    image = cv2.imread(str(p), cv2.IMREAD_GRAYSCALE)
    if image is None:
        return f"cannot read {p} as an image (unknown or damaged format)"
    return np.asarray(image, dtype=np.uint8)


@contextmanager
def progress_bars(enabled: bool) -> Iterator[Progress | None]:
    """A ``(stage, done, total)`` callback drawing one tqdm bar per stage on stderr, or None
    when disabled (``--json``: nothing but the JSON document is printed)."""
    if not enabled:
        yield None
        return
    from tqdm import tqdm

    bars: dict[str, Any] = {}

    def update(stage: str, done: int, total: int) -> None:
        bar = bars.get(stage)
        if bar is None:
            for other in bars.values():  # a new stage: the earlier ones are finished
                other.close()
            bar = bars[stage] = tqdm(total=total, desc=stage, file=sys.stderr, leave=True,
                                     dynamic_ncols=True,
                                     bar_format="{desc}: {percentage:3.0f}%|{bar}| "
                                                "{n_fmt}/{total_fmt} [{elapsed}]")
        bar.total = total
        bar.n = done
        bar.refresh()

    try:
        yield update
    finally:
        for bar in bars.values():
            bar.close()
