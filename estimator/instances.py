"""Every part in one frame: several copies of one dot layout, or of several layouts, at once.

The single-target search (:mod:`estimator.pipeline`) explains the frame's blobs with one
layout; with two identical plates in view two different matchings fit alike and it can only
call its answer ambiguous. Here the blobs are first grouped into candidate parts by their
image distance in imaged dot sizes (:mod:`estimator.grouping`), and each group is matched on
its own with the same correspondence search, POSIT seed and refinement
(:func:`estimator.correspondence.match_blobs`), trying every layout of the blobs' polarity
and keeping the one that explains most dots. A group that holds more than one part (parts
touching in the image) is split by position first; whatever a part leaves of a group is
matched again, and the blobs nothing explains are reported as unresolved. A part's
ambiguity is judged on its own blobs, so a second copy of the layout beside it is no
ambiguity.

A part's pose is good only when its dots are all there: each instance is flagged
``border`` when a dot of its layout lies at or past the image border at the pose found, and
``overlap`` when a dot the image should show is missing, when blobs that are not its own lie
on it, or when its dots' image overlaps another part's. An unresolved group is flagged
``border`` when the image border could cut off the rest of a part, and ``overlap`` when it
holds more dots than any layout.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, replace
from typing import Literal

import cv2
import numpy as np
from numpy.typing import NDArray

from estimator.ambiguity import MAX_DEG, MAX_DOT_MM
from estimator.blobs import BlobFilter, Polarity, detect_dots, threshold_spec
from estimator.camera import CameraModel
from estimator.correspondence import Correspondence, match_blobs
from estimator.errors import EstimationError
from estimator.grouping import group_blobs, link_span_dots, split_group
from estimator.result import Blob, PoseResult
from estimator.target import Target

Flag = Literal["border", "overlap"]
BORDER_CLEARANCE_PX = 2.0  # beyond half a dot: a dot centred nearer the edge may be cut


@dataclass(frozen=True)
class Instance:
    """One part found: its layout's name, its pose (blobs and dot ids filled) and why it may
    not be whole (``flags``, each with a sentence in ``reasons``)."""

    layout: str
    pose: PoseResult
    flags: tuple[Flag, ...] = ()
    reasons: tuple[str, ...] = ()


@dataclass(frozen=True)
class Unresolved:
    """Blobs that looked like one part and that no layout explains."""

    blobs: tuple[Blob, ...]
    flags: tuple[Flag, ...]
    reason: str

    @property
    def box_px(self) -> tuple[float, float, float, float]:
        """x0, y0, x1, y1 of the blobs' centres."""
        u = [b.u for b in self.blobs]
        v = [b.v for b in self.blobs]
        return min(u), min(v), max(u), max(v)


@dataclass(frozen=True)
class InstanceSearch:
    """What one frame shows: the parts found and the groups of blobs left unexplained."""

    instances: tuple[Instance, ...]
    unresolved: tuple[Unresolved, ...]
    n_blobs: int


@dataclass(frozen=True)
class _Match:
    layout: str
    blobs: NDArray[np.intp]  # indices into the polarity's blobs, in model-id order
    corr: Correspondence


class InstanceFinder:
    """Every instance of the named layouts in a frame; no state between frames.

    The options are :class:`estimator.Estimator`'s: ``max_missing`` dots a part may lack and
    still be solved, ``correct_bias``, the ambiguity thresholds and the detector's options.
    """

    def __init__(
        self,
        camera: CameraModel,
        layouts: Mapping[str, Target],
        *,
        max_missing: int = 1,
        correct_bias: bool = True,
        ambiguity_mm: float = MAX_DOT_MM,
        ambiguity_deg: float = MAX_DEG,
        **detector_options: float | str | None,
    ) -> None:
        if not layouts:
            raise ValueError("at least one layout is needed")
        self.camera = camera
        self.layouts = dict(layouts)
        self.max_missing = int(max_missing)
        self.correct_bias = correct_bias
        self.ambiguity = (float(ambiguity_mm), float(ambiguity_deg))
        opts = dict(detector_options)
        self._threshold = threshold_spec(opts.pop("threshold", None))
        try:
            self.filter = BlobFilter(**{k: float(v) for k, v in opts.items()})  # type: ignore[arg-type]
        except TypeError as err:
            raise ValueError(f"unknown detector option: {err}") from err

    def min_blobs(self, target: Target) -> int:
        return max(4, target.n_points - self.max_missing)

    def find(self, frame_u8: NDArray[np.uint8]) -> InstanceSearch:
        """Every part in the frame, in no particular order (the caller orders them)."""
        img = np.ascontiguousarray(frame_u8)
        found: list[Instance] = []
        unresolved: list[Unresolved] = []
        n_blobs = 0
        for polarity in sorted({t.polarity for t in self.layouts.values()}):
            layouts = {k: t for k, t in self.layouts.items() if t.polarity == polarity}
            blobs = self._detect(img, polarity, layouts)
            n_blobs += len(blobs)
            matches, leftover = self._resolve_all(blobs, layouts)
            found += self._judged(matches, blobs, img.shape)
            unresolved += [self._unresolved(blobs, g, layouts, img.shape) for g in leftover]
        return InstanceSearch(tuple(found), tuple(unresolved), n_blobs)

    def _detect(self, img: NDArray[np.uint8], polarity: Polarity,
                layouts: Mapping[str, Target]) -> list[Blob]:
        found, _ = detect_dots(img, polarity, self.filter, self._threshold)
        fewest = min(t.n_points for t in layouts.values())
        if len(found) < fewest:  # dots too small for the coarse pass?
            found, _ = detect_dots(img, polarity, self.filter, self._threshold, coarse=False)
        return found.blobs()

    def _resolve_all(self, blobs: list[Blob], layouts: Mapping[str, Target]
                     ) -> tuple[list[_Match], list[NDArray[np.intp]]]:
        if not blobs:
            return [], []
        centres = np.array([(b.u, b.v) for b in blobs], dtype=np.float64)
        axes = np.array([b.major_axis_px for b in blobs], dtype=np.float64)
        span = link_span_dots(list(layouts.values()))
        matches: list[_Match] = []
        leftover: list[NDArray[np.intp]] = []
        for group in group_blobs(centres, axes, span):
            got, rest = self._resolve_group(centres, group, layouts)
            matches += got
            if len(rest):
                leftover.append(rest)
        return matches, leftover

    def _resolve_group(self, centres: NDArray[np.float64], group: NDArray[np.intp],
                       layouts: Mapping[str, Target]) -> tuple[list[_Match], NDArray[np.intp]]:
        """The parts in one group: split by position when it holds room for several, then
        match each part and what the parts leave."""
        fewest = min(self.min_blobs(t) for t in layouts.values())
        typical = float(np.median([t.n_points for t in layouts.values()]))
        matches: list[_Match] = []
        pool = group
        if len(group) >= 2 * fewest:
            k = max(2, round(len(group) / typical))
            rests = []
            for part in split_group(centres[group], k):
                got, rest = self._peel(centres, group[part], layouts, fewest)
                matches += got
                rests.append(rest)
            pool = np.sort(np.concatenate(rests)) if rests else group[:0]
        got, rest = self._peel(centres, pool, layouts, fewest)
        return matches + got, rest

    def _peel(self, centres: NDArray[np.float64], pool: NDArray[np.intp],
              layouts: Mapping[str, Target], fewest: int
              ) -> tuple[list[_Match], NDArray[np.intp]]:
        """Match the pool's best part, take its blobs away, and again while any is found."""
        matches: list[_Match] = []
        while len(pool) >= fewest:
            m = self._best_match(centres, pool, layouts)
            if m is None:
                break
            pool = np.setdiff1d(pool, m.blobs)
            matches.append(m)
        return matches, pool

    def _best_match(self, centres: NDArray[np.float64], pool: NDArray[np.intp],
                    layouts: Mapping[str, Target]) -> _Match | None:
        """The layout explaining most of the pool's blobs (then the smallest rms)."""
        best: tuple[tuple[int, float, float], _Match] | None = None
        for name, target in layouts.items():
            if len(pool) < self.min_blobs(target):
                continue
            corr = self._match(centres[pool], target)
            if corr is None:
                continue
            chosen = pool[list(corr.blob_indices)]
            if len(chosen) < len(pool):  # the pool held more: judge the part on its own
                alone = self._match(centres[chosen], target)
                if alone is None:
                    continue
                chosen, corr = chosen[list(alone.blob_indices)], alone
            n = len(corr.model_ids)
            key = (n, n / target.n_points, -float(corr.pose.rms_px))
            if best is None or key > best[0]:
                best = (key, _Match(name, chosen, corr))
        return None if best is None else best[1]

    def _match(self, points_px: NDArray[np.float64], target: Target) -> Correspondence | None:
        try:
            return match_blobs(points_px, target, self.camera, max_missing=self.max_missing,
                               correct_bias=self.correct_bias, ambiguity=self.ambiguity)
        except EstimationError:
            return None

    def _judged(self, matches: list[_Match], blobs: list[Blob], shape: tuple[int, ...]
                ) -> list[Instance]:
        """Each match as an instance, with its border and overlap flags."""
        hulls = [self._dot_hull(m) for m in matches]
        centres = np.array([(b.u, b.v) for b in blobs], dtype=np.float64).reshape(-1, 2)
        out = []
        for i, m in enumerate(matches):
            target = self.layouts[m.layout]
            pose = replace(m.corr.pose, matched_blobs=tuple(blobs[k] for k in m.blobs),
                           matched_ids=m.corr.model_ids)
            flags: list[Flag] = []
            reasons: list[str] = []
            px = hulls[i]
            dot_px = max((blobs[k].major_axis_px for k in m.blobs), default=0.0)
            edge = 0.5 * dot_px + BORDER_CLEARANCE_PX
            h, w = shape[:2]
            off = ((px[:, 0] < edge) | (px[:, 0] > w - 1 - edge) | (px[:, 1] < edge)
                   | (px[:, 1] > h - 1 - edge))
            if off.any():
                flags.append("border")
                reasons.append(f"{int(off.sum())} of its {target.n_points} dots lie at or "
                               "past the image border")
            missing = [k for k in range(target.n_points)
                       if k not in m.corr.model_ids and not off[k]]
            if missing:
                reasons.append(f"dot(s) {missing} not seen where the image shows them: "
                               "hidden by something")
            foreign = self._foreign_blobs(px, dot_px, centres, m.blobs)
            if foreign:
                reasons.append(f"{foreign} blob(s) that are not its dots lie on it")
            others = [j for j in range(len(matches)) if j != i and _hulls_meet(px, hulls[j])]
            if others:
                reasons.append(f"its image overlaps {len(others)} other part(s)")
            if missing or foreign or others:
                flags.append("overlap")
            out.append(Instance(m.layout, pose, tuple(flags), tuple(reasons)))
        return out

    def _dot_hull(self, m: _Match) -> NDArray[np.float64]:
        """Where every dot of the layout projects at the part's pose (px)."""
        target = self.layouts[m.layout]
        T = m.corr.pose.T_camera_target
        Pc = target.points_mm @ T[:3, :3].T + T[:3, 3]
        return np.asarray(self.camera.project(Pc), dtype=np.float64)

    @staticmethod
    def _foreign_blobs(px: NDArray[np.float64], dot_px: float, centres: NDArray[np.float64],
                       own: NDArray[np.intp]) -> int:
        """Blobs not the part's own that lie inside its dots' hull grown by a dot."""
        others = np.setdiff1d(np.arange(len(centres)), own)
        if not len(others):
            return 0
        hull = cv2.convexHull(px.astype(np.float32))
        return sum(
            1 for k in others.tolist()
            if cv2.pointPolygonTest(hull, (float(centres[k, 0]), float(centres[k, 1])),
                                    True) > -dot_px)

    def _unresolved(self, blobs: list[Blob], group: NDArray[np.intp],
                    layouts: Mapping[str, Target], shape: tuple[int, ...]) -> Unresolved:
        chosen = tuple(blobs[k] for k in group.tolist())
        u = np.array([b.u for b in chosen])
        v = np.array([b.v for b in chosen])
        # How far a part's dots reach from any one of them, in px at these blobs' size.
        px_per_mm = float(np.median([b.major_axis_px for b in chosen])) / min(
            t.dot_diameter_mm for t in layouts.values())
        reach = px_per_mm * max(_diameter_mm(t) for t in layouts.values())
        h, w = shape[:2]
        near_edge = min(u.min(), v.min(), w - 1 - u.max(), h - 1 - v.max()) < reach
        most = max(t.n_points for t in layouts.values())
        flags: list[Flag] = []
        if near_edge and len(chosen) < most:
            flags.append("border")
            reason = (f"{len(chosen)} dot(s) near the image border: a part cut off by it "
                      "cannot be solved")
        elif len(chosen) > most:
            flags.append("overlap")
            reason = (f"{len(chosen)} dots together, more than any layout has: parts that "
                      "overlap, or clutter")
        else:
            reason = f"{len(chosen)} dot(s) that no layout explains"
        return Unresolved(chosen, tuple(flags), reason)


def _diameter_mm(target: Target) -> float:
    """The largest distance between two dots of the layout."""
    pts = target.points_mm
    return float(np.linalg.norm(pts[:, None] - pts[None], axis=2).max())


def _hulls_meet(a_px: NDArray[np.float64], b_px: NDArray[np.float64]) -> bool:
    """Whether the convex hulls of two parts' projected dots overlap."""
    area, _ = cv2.intersectConvexConvex(cv2.convexHull(a_px.astype(np.float32)),
                                        cv2.convexHull(b_px.astype(np.float32)))
    return bool(area > 0.0)
