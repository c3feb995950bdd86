"""Files the cell keeps in its state dir, written so that a crash never leaves half of one.

Taught poses, recipes and the PLC's remembered mode are small JSON files a person may also
read; each write goes to a temporary file beside the target, is synced, and replaces the old
one in one rename, so a reader (or the next start) sees the old file or the new, never a mix.
"""

from __future__ import annotations

import os
import tempfile
from pathlib import Path


def replace_text(path: Path, text: str) -> None:
    """Write ``text`` to ``path`` atomically (OSError when it cannot; ``path`` is then as it
    was, and no temporary file is left behind)."""
    tmp: str | None = None
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", dir=path.parent)
        with os.fdopen(fd, "w") as f:
            f.write(text)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
        tmp = None
    finally:
        if tmp is not None:
            Path(tmp).unlink(missing_ok=True)
