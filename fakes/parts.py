"""The parts in the simulated world: where each truly is, and which one the gripper holds.

Each part is a dot layout (what the camera sees of it), a width (what the fingers close on) and
a true pose in the base frame, fixed or drifting at a constant velocity from when it was placed
(a conveyor). The simulated camera renders every part in view from :meth:`SimParts.scene_at`;
the simulated gripper asks :meth:`SimParts.grip` when its fingers start to close.

The grasp pose of a part is its frame's origin with the tool's z axis along the part's +z (the
target frame's +z points into the plate: the tool looks into the part, as an approach with an
identity ``T_target_tcp`` and no standoff ends). Closing grips the part whose grasp pose is
nearest the true TCP within the fingers' reach: the TCP at most :data:`GRASP_LATERAL_MM` from
the origin across the tool axis and :data:`GRASP_AXIAL_MM` along it, the tool axis at most
:data:`GRASP_TILT_DEG` off the part's normal; the turn about the tool axis is free (the part is
as wide across every direction the fingers may close in). A part wider than the fingers' opening
does not fit between them, one narrower than where they are asked to stop is not touched.

A held part rides on the flange (``T_flange_part`` fixed when the fingers closed), so its truth
follows the arm wherever the arm really is; opening the fingers leaves it at its last true pose,
standing still.

A part may be a fixed reference: a dot plate clamped in the cell (a calibration check's
reference), which never drifts and which the fingers never take. Two faults move parts without
the cell knowing, each undone by clearing it: a knock of every fixed reference
(:meth:`SimParts.set_reference_delta`, ``T_base_part @ delta``) and a slip of one part
(:meth:`SimParts.set_slip`, the same composition), which lasts until it is cleared or the part
is placed again or picked (its slipped pose is then simply where it lies).
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Protocol

import numpy as np
from numpy.typing import NDArray
from scipy.spatial.transform import Rotation

from estimator import Target
from estimator.transforms import invert_T

Matrix4 = NDArray[np.float64]
Vector3 = NDArray[np.float64]

GRASP_LATERAL_MM = 4.0  # a 2F-85's fingertip pads centre a part offset by a few mm
GRASP_AXIAL_MM = 4.0  # the pads are ~4 mm deep on either side of the grasp plane
GRASP_TILT_DEG = 5.0  # parallel fingers closing on a part tilted further than this slip
MAX_PARTS = 64
MAX_WIDTH_MM = 85.0  # the 2F-85's stroke


class PartPlacement(Protocol):
    """What to place: a layout by name (None: the cell's target), its dots, a true pose, an
    optional drift (base frame, from the moment of placing) and the width the fingers close on
    (None: the world's default)."""

    @property
    def layout_name(self) -> str | None: ...

    @property
    def layout(self) -> Target: ...

    @property
    def T_base_part(self) -> Matrix4: ...

    @property
    def velocity_mm_s(self) -> Vector3 | None: ...

    @property
    def angular_velocity_rad_s(self) -> Vector3 | None: ...

    @property
    def width_mm(self) -> float | None: ...

    @property
    def fixed_reference(self) -> bool: ...


@dataclass(frozen=True, eq=False)
class Placement:
    """A :class:`PartPlacement` in plain values."""

    layout: Target
    T_base_part: Matrix4
    layout_name: str | None = None
    velocity_mm_s: Vector3 | None = None
    angular_velocity_rad_s: Vector3 | None = None
    width_mm: float | None = None
    fixed_reference: bool = False


@dataclass(frozen=True, eq=False)
class PartTruth:
    """One part's truth at one instant; ``T_tcp_part`` is where it sits in the closed fingers
    (None unless held)."""

    id: int
    layout_name: str | None
    layout: Target
    T_base_part: Matrix4
    held: bool
    width_mm: float
    velocity_mm_s: Vector3
    T_tcp_part: Matrix4 | None = None
    fixed_reference: bool = False
    T_slip: Matrix4 | None = None  # the slip it carries (T_base_part = placed @ T_slip)


@dataclass
class _Part:
    layout_name: str | None
    layout: Target
    T_base_part0: Matrix4
    t0_s: float
    velocity_mm_s: Vector3
    angular_velocity_rad_s: Vector3
    width_mm: float
    fixed_reference: bool = False
    T_flange_part: Matrix4 | None = field(default=None)  # held: where it sits on the flange
    T_slip: Matrix4 | None = field(default=None)  # slipped without the cell knowing

    def placed_at(self, t_s: float) -> Matrix4:
        """Where the part was put, at ``t_s``: placed, moved on at its velocity (translation
        of its origin, rotation about it, base frame)."""
        dt = t_s - self.t0_s
        T = self.T_base_part0.copy()
        if np.any(self.angular_velocity_rad_s):
            turn = Rotation.from_rotvec(self.angular_velocity_rad_s * dt).as_matrix()
            T[:3, :3] = turn @ T[:3, :3]
        T[:3, 3] += self.velocity_mm_s * dt
        return T


def grasp_error(T_base_part: Matrix4, T_base_tcp: Matrix4) -> tuple[float, float, float]:
    """``(lateral_mm, axial_mm, tilt_deg)`` of the TCP from the part's grasp pose."""
    p = (invert_T(T_base_part) @ np.r_[T_base_tcp[:3, 3], 1.0])[:3]
    cos_tilt = float(np.clip(T_base_part[:3, 2] @ T_base_tcp[:3, 2], -1.0, 1.0))
    return float(np.hypot(p[0], p[1])), abs(float(p[2])), float(np.degrees(np.arccos(cos_tilt)))


def in_grasp(T_base_part: Matrix4, T_base_tcp: Matrix4) -> bool:
    """Whether fingers closing at ``T_base_tcp`` take the part at ``T_base_part``."""
    lateral, axial, tilt = grasp_error(T_base_part, T_base_tcp)
    return lateral <= GRASP_LATERAL_MM and axial <= GRASP_AXIAL_MM and tilt <= GRASP_TILT_DEG


def _vector(v: Vector3 | None, name: str) -> Vector3:
    out = np.zeros(3) if v is None else np.asarray(v, dtype=float)
    if out.shape != (3,) or not np.all(np.isfinite(out)):
        raise ValueError(f"{name} must be 3 finite values")
    return out.copy()


class SimParts:
    """The parts of one simulated world (thread-safe); time is ``clock``'s."""

    def __init__(self, parts: Sequence[PartPlacement], default_width_mm: float = 40.0,
                 clock: Callable[[], float] = time.monotonic) -> None:
        self.default_width_mm = self._width(default_width_mm)
        self._clock = clock
        self._lock = threading.Lock()
        self._parts: list[_Part] = self._parse(parts)
        self._T_reference_delta: Matrix4 | None = None

    @staticmethod
    def one(layout: Target, T_base_part: Matrix4, width_mm: float = 40.0) -> SimParts:
        """A world of one part (the cell's target), ``width_mm`` wide."""
        return SimParts([Placement(layout, T_base_part)], width_mm)

    def now(self) -> float:
        return self._clock()

    # -- placing -------------------------------------------------------------------------------
    def place(self, parts: Sequence[PartPlacement]) -> None:
        """Replace every part (the held one too: the fingers now hold nothing) with
        ``parts``, numbered in order from 0. ValueError, with nothing changed, for a pose, a
        velocity or a width the world cannot take, or no part at all."""
        parsed = self._parse(parts)
        with self._lock:
            self._parts = parsed

    def place_first(self, T_base_part: Matrix4, velocity_mm_s: Vector3 | None = None,
                    angular_velocity_rad_s: Vector3 | None = None) -> None:
        """Put part 0 (its layout and width kept) at ``T_base_part`` now, drifting from now on
        at the velocities given; out of the fingers if they held it. The other parts stay."""
        T = self._pose(T_base_part)
        v = _vector(velocity_mm_s, "velocity_mm_s")
        w = _vector(angular_velocity_rad_s, "angular_velocity_rad_s")
        with self._lock:
            first = self._parts[0]
            if first.fixed_reference and (np.any(v) or np.any(w)):
                raise ValueError("part 0 is a fixed reference: it does not drift")
            self._parts[0] = _Part(first.layout_name, first.layout, T, self._clock(), v, w,
                                   first.width_mm, first.fixed_reference)

    def _parse(self, parts: Sequence[PartPlacement]) -> list[_Part]:
        if not 1 <= len(parts) <= MAX_PARTS:
            raise ValueError(f"a world holds 1 to {MAX_PARTS} parts, got {len(parts)}")
        t0 = self._clock()
        out = []
        for i, p in enumerate(parts):
            try:
                width = self.default_width_mm if p.width_mm is None else self._width(p.width_mm)
                v = _vector(p.velocity_mm_s, "velocity_mm_s")
                w = _vector(p.angular_velocity_rad_s, "angular_velocity_rad_s")
                if p.fixed_reference and (np.any(v) or np.any(w)):
                    raise ValueError("a fixed reference does not drift")
                out.append(_Part(p.layout_name, p.layout, self._pose(p.T_base_part), t0, v, w,
                                 width, bool(p.fixed_reference)))
            except ValueError as err:
                raise ValueError(f"part {i}: {err}") from err
        return out

    @staticmethod
    def _pose(T: Matrix4, name: str = "T_base_part") -> Matrix4:
        out = np.array(T, dtype=float)
        if out.shape != (4, 4) or not np.all(np.isfinite(out)):
            raise ValueError(f"{name} must be a finite 4x4 transform")
        return out

    # -- faults --------------------------------------------------------------------------------
    def has_fixed_reference(self) -> bool:
        with self._lock:
            return any(p.fixed_reference for p in self._parts)

    def set_reference_delta(self, T_delta: Matrix4 | None) -> None:
        """Knock every fixed reference, now and any placed later, to ``T_base_part @
        T_delta`` from where it was placed (None: back where it was placed)."""
        T = None if T_delta is None else self._pose(T_delta, "the reference's delta")
        with self._lock:
            self._T_reference_delta = T

    def reference_delta(self) -> Matrix4 | None:
        with self._lock:
            return None if self._T_reference_delta is None else self._T_reference_delta.copy()

    def set_slip(self, part_id: int, T_slip: Matrix4) -> None:
        """Slip part ``part_id`` to ``T_base_part @ T_slip`` from where it was placed, in
        place of any slip it had. ValueError, nothing changed, for a part that does not exist,
        is a fixed reference or is in the fingers."""
        T = self._pose(T_slip, "the slip")
        with self._lock:
            if not 0 <= part_id < len(self._parts):
                raise ValueError(f"no part {part_id}: the world holds {len(self._parts)}")
            part = self._parts[part_id]
            if part.fixed_reference:
                raise ValueError(f"part {part_id} is a fixed reference: knock it with the "
                                 f"reference's delta")
            if part.T_flange_part is not None:
                raise ValueError(f"part {part_id} is in the gripper")
            part.T_slip = T

    def clear_slips(self) -> None:
        """Every slipped part back where it was placed."""
        with self._lock:
            for p in self._parts:
                p.T_slip = None

    def slips(self) -> dict[int, Matrix4]:
        """The parts that lie slipped, by id, and their slips."""
        with self._lock:
            return {i: p.T_slip.copy() for i, p in enumerate(self._parts)
                    if p.T_slip is not None}

    @staticmethod
    def _width(width_mm: float) -> float:
        if not 0.0 < width_mm <= MAX_WIDTH_MM:
            raise ValueError(f"width_mm must be within (0, {MAX_WIDTH_MM:g}], got {width_mm}")
        return float(width_mm)

    # -- truth ---------------------------------------------------------------------------------
    def first_layout(self) -> Target:
        """Part 0's dot layout."""
        with self._lock:
            return self._parts[0].layout

    def first_at(self, t_s: float, flange: Callable[[], Matrix4]) -> Matrix4:
        """Part 0's true pose at ``t_s``; held, where ``flange()`` (the flange's true pose)
        puts it."""
        with self._lock:
            first = self._parts[0]
            if first.T_flange_part is None:
                return self._lying_at(first, t_s)
            T_flange_part = first.T_flange_part
        return np.asarray(flange() @ T_flange_part, dtype=float)

    def scene_at(self, t_s: float, T_base_flange: Matrix4) -> list[tuple[Target, Matrix4]]:
        """Every part's layout and true pose at ``t_s``, the flange then at ``T_base_flange``
        (what a camera exposed at ``t_s`` sees)."""
        with self._lock:
            return [(p.layout, self._pose_at(p, t_s, T_base_flange)) for p in self._parts]

    def truth(self, t_s: float, T_base_flange: Matrix4, T_base_tcp: Matrix4) -> list[PartTruth]:
        """Every part's truth at ``t_s``, the flange and the TCP then where given."""
        with self._lock:
            out = []
            for i, p in enumerate(self._parts):
                T = self._pose_at(p, t_s, T_base_flange)
                held = p.T_flange_part is not None
                out.append(PartTruth(
                    i, p.layout_name, p.layout, T, held, p.width_mm,
                    np.zeros(3) if held else p.velocity_mm_s.copy(),
                    invert_T(T_base_tcp) @ T if held else None, p.fixed_reference,
                    None if p.T_slip is None else p.T_slip.copy()))
            return out

    def _pose_at(self, p: _Part, t_s: float, T_base_flange: Matrix4) -> Matrix4:
        if p.T_flange_part is not None:
            return np.asarray(T_base_flange @ p.T_flange_part, dtype=float)
        return self._lying_at(p, t_s)

    def _lying_at(self, p: _Part, t_s: float) -> Matrix4:
        """Where a part not held truly lies at ``t_s``: where it was put, slipped or knocked
        (call with the lock held)."""
        T = p.placed_at(t_s)
        if p.T_slip is not None:
            T = T @ p.T_slip
        if p.fixed_reference and self._T_reference_delta is not None:
            T = T @ self._T_reference_delta
        return T

    # -- the fingers ---------------------------------------------------------------------------
    def grip(self, t_s: float, T_base_flange: Matrix4, T_base_tcp: Matrix4, opening_mm: float,
             closing_to_mm: float) -> float | None:
        """Fingers ``opening_mm`` apart start closing towards ``closing_to_mm`` with the arm
        truly at ``T_base_flange`` / ``T_base_tcp`` at ``t_s``: the width of the part they
        close on, which is held from now on, or None (they close on nothing)."""
        with self._lock:
            for p in self._parts:
                if p.T_flange_part is not None:  # closing on the part already held
                    return p.width_mm if closing_to_mm < p.width_mm else None
            best: tuple[float, _Part] | None = None
            for p in self._parts:
                if p.fixed_reference or not closing_to_mm < p.width_mm <= opening_mm + 1e-9:
                    continue
                T = self._lying_at(p, t_s)
                if not in_grasp(T, T_base_tcp):
                    continue
                lateral, axial, _ = grasp_error(T, T_base_tcp)
                if best is None or np.hypot(lateral, axial) < best[0]:
                    best = (float(np.hypot(lateral, axial)), p)
            if best is None:
                return None
            part = best[1]
            part.T_flange_part = invert_T(T_base_flange) @ self._lying_at(part, t_s)
            part.T_slip = None  # picked where it lay: the slip is now its pose in the fingers
            return part.width_mm

    def release(self, t_s: float, T_base_flange: Matrix4) -> None:
        """The fingers open: a held part stays where it truly is now, still."""
        with self._lock:
            for p in self._parts:
                if p.T_flange_part is not None:
                    p.T_base_part0 = np.asarray(T_base_flange @ p.T_flange_part, dtype=float)
                    p.t0_s = t_s
                    p.velocity_mm_s = np.zeros(3)
                    p.angular_velocity_rad_s = np.zeros(3)
                    p.T_flange_part = None
