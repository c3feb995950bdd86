"""Taught reference poses: ``T_target_tcp`` stored under a name, so ``approach`` can reuse it.

Teaching: with the arm resting where the tool should be relative to the target (a grasp pose,
reached by jogging) and the target in the camera's view, several locates from distinct frames
are turned into ``T_target_tcp = inv(T_base_target) @ T_base_tcp`` and averaged. Their spread
(largest distance of one sample from the mean, mm and deg) is reported and a spread over the
limit is refused, because a noisy or moving scene would otherwise be stored as if it were exact.

Store: one JSON file, ``taught_poses.json`` beside the job database (``[api] job_db``). JSON
rather than a table in the job database because a person copies taught poses between cells
and reads them in a text editor; beside the job database because that is the cell's writable
state directory (the config file may be read-only and is hand-edited). Every change rewrites
the whole file atomically (temporary file, fsync, rename), so a crash leaves either the old
or the new file, never a torn one. A file that cannot be read is never overwritten.

A place pose is taught in the base frame (``frame="base"``): the resting TCP itself, averaged
over several readings of the arm, with no target in it; a pick releases its part there. Such a
pose has no ``T_target_tcp`` and is refused where a tool pose relative to the target is asked
for (``taught_wrong_frame``), as a target-relative pose is refused as a place pose.

Teaching by showing: the view is recorded too (``view``: each matched dot's normalised image
point and depth, averaged over the samples), so an IBVS approach
(:mod:`cell.servoing.image`) can drive the image back to it. Poses taught before that have
no view; they still serve servo and look-and-move, and IBVS to them is refused
(``taught_without_view``).
"""

from __future__ import annotations

import json
import re
import threading
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal, Protocol

import numpy as np
from numpy.typing import NDArray

from cell.core import CellCore
from cell.error_codes import ErrorCode
from cell.errors import CellError, LimitError, NotFoundError, RefusedError
from cell.files import replace_text
from cell.results.modes import ApproachMode
from cell.servoing.ibvs import Features, features_from_view
from cell.servoing.ibvs_settle import mean_features
from cell.vision.frames import mean_pose
from cell.vision.locate import Located, Locator
from drivers.arm import ArmState
from estimator.transforms import T_from_pose_dict, invert_T, pose_dict, pose_distance

Matrix4 = NDArray[np.float64]

STORE_NAME = "taught_poses.json"
FORMAT_VERSION = 1
NAME_PATTERN = re.compile(r"^[A-Za-z0-9][A-Za-z0-9_.\-]{0,63}$")
DEFAULT_MAX_SPREAD_MM = 0.5
DEFAULT_MAX_SPREAD_DEG = 0.2
# The arm must rest while teaching: a TCP that moves more than this between samples is refused.
STILL_MM = 0.05
STILL_DEG = 0.02
TaughtFrame = Literal["target", "base"]


class TeachStoreError(CellError):
    """The store file cannot be read or written; nothing was changed."""

    kind = "unavailable"


@dataclass(frozen=True)
class TaughtPose:
    name: str
    T_target_tcp: Matrix4 | None  # None: a base-frame pose
    samples: int
    spread_mm: float  # largest distance of one sample from the mean
    spread_deg: float
    T_base_target: Matrix4 | None  # where the target was when taught (None: a base-frame pose)
    T_base_tcp: Matrix4
    taught_by: str
    taught_at: float  # UNIX seconds
    view: Features | None = None  # the desired image features (None: taught without them)
    frame: TaughtFrame = "target"

    def as_dict(self) -> dict[str, Any]:
        return {**self._pose_dict(), "view": view_dict(self.view)}

    def _pose_dict(self) -> dict[str, Any]:
        return {
            "name": self.name, "frame": self.frame,
            "T_target_tcp": _pose_or_none(self.T_target_tcp),
            "samples": self.samples, "spread_mm": self.spread_mm, "spread_deg": self.spread_deg,
            "T_base_target": _pose_or_none(self.T_base_target),
            "T_base_tcp": pose_dict(self.T_base_tcp),
            "taught_by": self.taught_by, "taught_at": self.taught_at,
        }

    @staticmethod
    def from_dict(d: dict[str, Any]) -> TaughtPose:
        frame: TaughtFrame = "base" if d.get("frame") == "base" else "target"
        return TaughtPose(
            name=str(d["name"]), T_target_tcp=_T_or_none(d.get("T_target_tcp")),
            samples=int(d["samples"]), spread_mm=float(d["spread_mm"]),
            spread_deg=float(d["spread_deg"]), T_base_target=_T_or_none(d.get("T_base_target")),
            T_base_tcp=T_from_pose_dict(d["T_base_tcp"]), taught_by=str(d["taught_by"]),
            taught_at=float(d["taught_at"]),
            view=view_from_dict(d.get("view"), int(d["samples"])), frame=frame)

    def tool_pose(self) -> Matrix4:
        """``T_target_tcp``; a base-frame pose is refused (``taught_wrong_frame``)."""
        if self.T_target_tcp is None:
            raise LimitError(ErrorCode.taught_wrong_frame,
                             f"the pose {self.name!r} is taught in the base frame (a place "
                             "pose): a job that approaches a target needs a pose taught "
                             "relative to the target")
        return self.T_target_tcp

    def place_pose(self) -> Matrix4:
        """``T_base_tcp`` of a base-frame pose; a target-relative one is refused
        (``taught_wrong_frame``): where it puts the tool depends on where a target was."""
        if self.frame != "base":
            raise LimitError(ErrorCode.taught_wrong_frame,
                             f"the pose {self.name!r} is taught relative to the target; a "
                             "place pose is taught in the base frame (POST /teach with "
                             "frame \"base\")")
        return self.T_base_tcp


def _pose_or_none(T: Matrix4 | None) -> dict[str, Any] | None:
    return None if T is None else pose_dict(T)


def _T_or_none(d: dict[str, Any] | None) -> Matrix4 | None:
    return None if d is None else T_from_pose_dict(d)


def view_dict(view: Features | None) -> dict[str, Any] | None:
    if view is None:
        return None
    return {"ids": list(view.ids), "xy": view.xy.tolist(), "depth_mm": view.depth_mm.tolist(),
            "frames": view.frames}


def view_from_dict(d: dict[str, Any] | None, frames: int = 1) -> Features | None:
    """``frames``: how many frames the view averages when the record does not say (a pose
    taught before the record kept it: one frame a sample)."""
    if d is None:
        return None
    xy = np.asarray(d["xy"], dtype=float).reshape(-1, 2)
    depth = np.asarray(d["depth_mm"], dtype=float).reshape(-1)
    ids = tuple(int(i) for i in d["ids"])
    if len(ids) != len(xy) or len(ids) != len(depth):
        raise ValueError("a taught view needs one point and one depth per dot id")
    return Features(ids, xy, depth, max(1, int(d.get("frames", frames))))


def mean_view(views: list[Features]) -> Features | None:
    """The dots seen in every view, their normalised points and depths averaged (views of
    one frame each, or means of equally many frames); None when no dot is in all of them."""
    if not views or not any(all(i in v.ids for v in views[1:]) for i in views[0].ids):
        return None
    return mean_features(views)


def check_name(name: str) -> str:
    if not NAME_PATTERN.match(name):
        raise LimitError(ErrorCode.invalid_name,
                         f"taught pose name {name!r}: use 1-64 letters, digits, "
                         "'_', '.' or '-', starting with a letter or digit")
    return name


class TaughtStore:
    """Thread-safe named poses in one JSON file (``path=None``: in memory only, for tests and
    an in-memory job database)."""

    def __init__(self, path: str | Path | None) -> None:
        self.path = None if path is None else Path(path)
        self._lock = threading.Lock()
        self._error: TeachStoreError | None = None
        self._poses: dict[str, TaughtPose] = {}
        try:
            self._poses = self._load()
        except TeachStoreError as err:  # the service still runs; taught poses are refused
            self._error = err

    @staticmethod
    def beside_job_db(job_db: str) -> TaughtStore:
        if job_db == ":memory:":
            return TaughtStore(None)
        return TaughtStore(Path(job_db).parent / STORE_NAME)

    def _load(self) -> dict[str, TaughtPose]:
        if self.path is None or not self.path.exists():
            return {}
        try:
            data = json.loads(self.path.read_text())
            return {d["name"]: TaughtPose.from_dict(d) for d in data["poses"]}
        except (OSError, ValueError, KeyError, TypeError) as err:
            raise TeachStoreError(ErrorCode.taught_store_unreadable,
                                  f"cannot read the taught poses in {self.path}: {err!r}; fix or "
                                  "move the file (it is never overwritten while unreadable)"
                                  ) from err

    def list(self) -> list[TaughtPose]:
        self._usable()
        with self._lock:
            return sorted(self._poses.values(), key=lambda p: p.name)

    def has(self, name: str) -> bool:
        self._usable()
        with self._lock:
            return name in self._poses

    def get(self, name: str) -> TaughtPose:
        """The pose taught under ``name``; anything but a taught name (a PLC may send a number
        or an array) is ``taught_not_found``."""
        self._usable()
        with self._lock:
            pose = self._poses.get(name) if isinstance(name, str) else None
        if pose is None:
            raise NotFoundError(ErrorCode.taught_not_found, f"no taught pose named {name!r}; see "
                                "GET /api/v1/teach for the taught names")
        return pose

    def for_job(self, name: str | None, mode: str | None
                ) -> tuple[Matrix4 | None, Features | None]:
        """The taught pose a job names (None: none) as the job takes it: its ``T_target_tcp``
        and, for mode ``ibvs``, the view it converges on. Every interface refuses alike:
        ``ibvs_needs_taught`` (ibvs without a name), ``taught_not_found``,
        ``taught_without_view`` (ibvs to a pose taught before views were recorded)."""
        ibvs = mode == ApproachMode.ibvs
        if name is None:
            if ibvs:
                raise LimitError(ErrorCode.ibvs_needs_taught,
                                 "mode 'ibvs' converges on a taught view: give the taught "
                                 "pose's name (teaching records its view)")
            return None, None
        pose = self.get(name)
        T_target_tcp = pose.tool_pose()
        if ibvs and pose.view is None:
            raise LimitError(ErrorCode.taught_without_view,
                             f"the pose {name!r} was taught without its view (an older "
                             "record): it serves servo and look_and_move; teach it again for "
                             "ibvs")
        return T_target_tcp, pose.view if ibvs else None

    def put(self, pose: TaughtPose, replace: bool = True) -> None:
        self._usable()
        check_name(pose.name)
        with self._lock:
            if not replace and pose.name in self._poses:
                raise RefusedError(ErrorCode.taught_exists,
                                   f"a pose named {pose.name!r} is already "
                                   "taught; delete it first or ask to replace it")
            poses = {**self._poses, pose.name: pose}
            self._write(poses)
            self._poses = poses

    def delete(self, name: str) -> TaughtPose:
        self._usable()
        with self._lock:
            pose = self._poses.get(name)
            if pose is None:
                raise NotFoundError(ErrorCode.taught_not_found, f"no taught pose named {name!r}")
            poses = {k: v for k, v in self._poses.items() if k != name}
            self._write(poses)
            self._poses = poses
            return pose

    def _usable(self) -> None:
        if self._error is not None:
            raise self._error

    def _write(self, poses: dict[str, TaughtPose]) -> None:
        """Replace the file atomically; on failure the file and the memory stay as they were."""
        if self.path is None:
            return
        text = json.dumps({"version": FORMAT_VERSION,
                           "poses": [p.as_dict() for p in sorted(poses.values(),
                                                                 key=lambda p: p.name)]},
                          indent=2)
        try:
            replace_text(self.path, text + "\n")
        except OSError as err:
            raise TeachStoreError(ErrorCode.taught_store_write_failed,
                                  f"cannot write {self.path}: {err}; nothing was changed") from err


@dataclass(frozen=True)
class Sample:
    """One locate (or the mean of several): the target and the resting TCP, at the frames'
    capture times."""

    T_base_target: Matrix4
    T_base_tcp: Matrix4
    frame_sequence: int
    view: Features | None = None


def combine(name: str, samples: list[Sample], caller: str, max_spread_mm: float,
            max_spread_deg: float) -> TaughtPose:
    """Average the samples into a taught pose; refuse a moving arm or a spread over the limit."""
    if not samples:
        raise LimitError(ErrorCode.invalid_request, "teaching needs at least one sample")
    require_still([s.T_base_tcp for s in samples])
    each = [invert_T(s.T_base_target) @ s.T_base_tcp for s in samples]
    T_mean = mean_pose(each)
    dists = [pose_distance(T_mean, T) for T in each]
    spread_mm = max(d[0] for d in dists)
    spread_deg = max(d[1] for d in dists)
    if spread_mm > max_spread_mm or spread_deg > max_spread_deg:
        raise RefusedError(ErrorCode.spread_too_large, f"the {len(samples)} locates spread "
                           f"{spread_mm:.3f} mm / {spread_deg:.3f} deg (limit {max_spread_mm} mm"
                           f" / {max_spread_deg} deg): the view is poor or the target moves; "
                           "nothing was stored")
    T_base_target = mean_pose([s.T_base_target for s in samples])
    T_base_tcp = mean_pose([s.T_base_tcp for s in samples])
    return TaughtPose(check_name(name), T_mean, len(samples), spread_mm, spread_deg,
                      T_base_target, T_base_tcp, caller, time.time(),
                      mean_view([s.view for s in samples if s.view is not None])
                      if all(s.view is not None for s in samples) else None)


class TeachingCell(Protocol):
    """What teaching uses of the running cell (:class:`cell.service.Cell` teaches with itself):
    its shared parts, the arm's state and the audited locate."""

    core: CellCore

    def arm_state(self) -> ArmState: ...

    def locate(self, caller: str, n_frames: int = 1) -> Located: ...


def teach(cell: TeachingCell, store: TaughtStore, caller: str, name: str, samples: int = 5,
          max_spread_mm: float = DEFAULT_MAX_SPREAD_MM,
          max_spread_deg: float = DEFAULT_MAX_SPREAD_DEG, replace: bool = True,
          frame: TaughtFrame = "target") -> TaughtPose:
    """Store the pose at the arm's resting pose under ``name``: relative to the target
    (``samples`` locates from distinct frames, their ``T_target_tcp`` averaged), or in the base
    frame (``samples`` readings of the resting TCP, no camera). Nothing moves; every refusal
    stores nothing."""
    params = {"name": name, "samples": samples, "max_spread_mm": max_spread_mm,
              "max_spread_deg": max_spread_deg, "replace": replace, "frame": frame}
    with cell.core.audit.command(caller, "teach", params) as note:
        check_name(name)
        if frame not in ("target", "base"):
            raise LimitError(ErrorCode.invalid_request,
                             f"frame must be 'target' or 'base', got {frame!r}")
        if not 1 <= samples <= 50:
            raise LimitError(ErrorCode.invalid_request, "samples must be 1..50")
        if not replace and store.has(name):
            raise RefusedError(ErrorCode.taught_exists, f"a pose named {name!r} is already taught; "
                               "delete it first or ask to replace it")
        # Hold the motion slot: no approach or jog may start while the samples are taken,
        # and a running one refuses the teach (busy).
        with cell.core.slot.hold("teach"):
            if cell.arm_state().moving:
                raise RefusedError(ErrorCode.arm_moving, "the arm is moving; teach when it rests")
            if frame == "base":
                taught = combine_base(name, _tcp_samples(cell, samples), caller)
            else:
                per_sample = cell.core.config.teach.frames_per_sample
                taught = combine(name, _samples(cell, caller, samples, per_sample), caller,
                                 max_spread_mm, max_spread_deg)
        store.put(taught, replace=replace)
        frames = f", {taught.view.frames} frames" if taught.view is not None else ""
        note.detail = f"spread {taught.spread_mm:.3f} mm / {taught.spread_deg:.3f} deg{frames}"
    return taught


def require_still(tcps: list[Matrix4]) -> None:
    """Refuse (``arm_moving``) TCP readings that moved from the first by more than the rest
    allows: a teach averages a resting arm's views, not a path."""
    for T in tcps[1:]:
        d_mm, d_deg = pose_distance(tcps[0], T)
        if d_mm > STILL_MM or d_deg > STILL_DEG:
            raise RefusedError(ErrorCode.arm_moving,
                               f"the arm moved {d_mm:.3f} mm / {d_deg:.3f} deg "
                               "while teaching; let it rest and teach again")


def combine_base(name: str, tcps: list[Matrix4], caller: str) -> TaughtPose:
    """A base-frame pose from resting TCP readings; an arm that moved between them is refused."""
    require_still(tcps)
    T_mean = mean_pose(tcps)
    dists = [pose_distance(T_mean, T) for T in tcps]
    return TaughtPose(check_name(name), None, len(tcps), max(d[0] for d in dists),
                      max(d[1] for d in dists), None, T_mean, caller, time.time(), frame="base")


def _tcp_samples(cell: TeachingCell, n: int) -> list[Matrix4]:
    """``n`` readings of the resting TCP, one controller state apart."""
    out: list[Matrix4] = []
    for i in range(n):
        if i:
            time.sleep(0.01)
        out.append(np.asarray(cell.arm_state().T_base_tcp, dtype=float))
    return out


def located_view(locator: Locator, loc: Located) -> Features | None:
    """The image features of a locate's last frame (None when it kept no image points)."""
    r = loc.result
    if r.image_points_px is None or not r.matched_ids:
        return None
    return features_from_view(locator.camera_model, r.matched_ids, r.image_points_px,
                              r.T_camera_target, locator.target.points_mm)


def _samples(cell: TeachingCell, caller: str, n: int, per_sample: int = 1) -> list[Sample]:
    """``n`` samples, each the mean of ``per_sample`` locates from frames not used before (the
    camera runs at its own rate). The spread is judged between samples, so a mean of several
    frames is held to the same limit as one frame was."""
    frames = _frames(cell, caller, n * per_sample)
    return [_mean_sample(frames[k:k + per_sample]) for k in range(0, len(frames), per_sample)]


def _mean_sample(frames: list[Sample]) -> Sample:
    if len(frames) == 1:
        return frames[0]
    require_still([s.T_base_tcp for s in frames])
    views = [s.view for s in frames if s.view is not None]
    return Sample(mean_pose([s.T_base_target for s in frames]),
                  mean_pose([s.T_base_tcp for s in frames]), frames[-1].frame_sequence,
                  mean_view(views) if len(views) == len(frames) else None)


def _frames(cell: TeachingCell, caller: str, n: int) -> list[Sample]:
    """``n`` locates, each from a frame not used before."""
    period_s = 1.0 / cell.core.config.camera.fps
    deadline = time.monotonic() + 5.0 + 3.0 * n * period_s
    out: list[Sample] = []
    seen: set[int] = set()
    while len(out) < n:
        loc = cell.locate(caller, 1)
        if loc.frame_sequence in seen:
            if time.monotonic() > deadline:
                raise RefusedError(ErrorCode.camera_stalled, "the camera delivers no new frames")
            time.sleep(0.5 * period_s)
            continue
        seen.add(loc.frame_sequence)
        out.append(Sample(loc.T_base_target, loc.T_base_tcp, loc.frame_sequence,
                          located_view(cell.core.locator, loc)))
    return out
