"""Part ids that stay put while the parts do: each locate's parts matched to those seen before.

A part keeps the id it had when it lies within ``same_part_mm`` (base frame, the centre of its
dots) of a part of the same layout seen in one of the last ``MEMORY_LOCATES`` locates; the
nearest pairs are matched first, each old id at most once. Any other part gets a new id,
counting up from 1 for the cell's lifetime, so an id is never given to two parts.
"""

from __future__ import annotations

import threading
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

MEMORY_LOCATES = 10  # a part hidden for a few locates (the arm over it) keeps its id


@dataclass
class _Seen:
    layout: str
    centre_mm: NDArray[np.float64]
    locate: int  # the locate it was last seen in


class InstanceIds:
    """Thread-safe: locates from different callers number their parts from one memory."""

    def __init__(self, same_part_mm: float) -> None:
        self.same_part_mm = float(same_part_mm)
        self._seen: dict[int, _Seen] = {}
        self._next = 1
        self._locates = 0
        self._lock = threading.Lock()

    def assign(self, parts: list[tuple[str, NDArray[np.float64]]]) -> list[int]:
        """The id of each (layout, centre in the base frame, mm) of one locate."""
        with self._lock:
            self._locates += 1
            now = self._locates
            self._seen = {k: s for k, s in self._seen.items()
                          if now - s.locate <= MEMORY_LOCATES}
            pairs = sorted(
                (float(np.linalg.norm(centre - s.centre_mm)), i, k)
                for i, (layout, centre) in enumerate(parts)
                for k, s in self._seen.items() if s.layout == layout)
            ids: list[int | None] = [None] * len(parts)
            taken: set[int] = set()
            for dist, i, k in pairs:
                if dist > self.same_part_mm:
                    break
                if ids[i] is None and k not in taken:
                    ids[i] = k
                    taken.add(k)
            out = []
            for i, (layout, centre) in enumerate(parts):
                got = ids[i]
                if got is None:
                    got, self._next = self._next, self._next + 1
                self._seen[got] = _Seen(layout, np.asarray(centre, dtype=float), now)
                out.append(got)
            return out

    def forget(self) -> None:
        """New mounts or a new calibration: base-frame positions seen before no longer
        compare, so every part gets a new id."""
        with self._lock:
            self._seen.clear()
