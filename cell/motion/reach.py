"""Whether the arm can take a pose, and the poses of a move, the way it will take them.

The checks solve the configured UR model's inverse kinematics
(:class:`estimator.inverse_kinematics.UrInverse`) with the TCP the arm is using, and refuse
with :class:`cell.errors.LimitError` ``unreachable`` a pose that has no joint solution, one
whose joints leave the configured joint range, or one closer to a singularity than the
configured margins (``[limits]``). Which solution counts is the one the controller will take:

- a straight move (moveL, a jog, a servo twist) keeps the configuration it starts in (the
  branch of the arm's joints): a pose reachable only in another one, or a path through a
  singularity, is refused, and the joints are followed along the sampled path so that a wrist
  turning past its range is caught where it happens;
- a joint move to a pose takes the solution nearest the joints it starts from.

As for the box and the tilt, an arm already inside a margin or outside the joint range (left
there by hand, or the limits tightened) may move, as long as it does not go deeper.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Protocol

import numpy as np
from numpy.typing import NDArray

from cell.config.schema import LimitsConfig
from cell.error_codes import ErrorCode
from cell.errors import LimitError
from estimator.inverse_kinematics import (
    Branch,
    Solutions,
    UrInverse,
    branch_of,
    unwrap_from,
    wrap_near,
)
from estimator.kinematics import UR_DH, forward
from estimator.transforms import invert_T

Matrix4 = NDArray[np.float64]
Joints = NDArray[np.float64]

JOINT_NAMES = ("base", "shoulder", "elbow", "wrist 1", "wrist 2", "wrist 3")
# Between two samples of a path (2 mm, 1 deg apart) no joint turns further than this outside a
# singularity's neighbourhood; a bigger turn is the configuration flipping through one.
MAX_JOINT_STEP_DEG = 30.0
_ON_SINGULARITY = 1e-9  # a factor this small: the configuration belongs to both sides


class ArmAt(Protocol):
    """Where the arm is: its joints and the TCP pose they give (an :class:`ArmState`)."""

    @property
    def joints_rad(self) -> Joints: ...

    @property
    def T_base_tcp(self) -> Matrix4: ...


@dataclass(frozen=True)
class Posture:
    """Joints and the TCP pose they give, for a pose not yet reached."""

    joints_rad: Joints
    T_base_tcp: Matrix4


class ReachCheck:
    """The configured arm model's reach, joint range and singularity margins."""

    def __init__(self, limits: LimitsConfig, model: str) -> None:
        self.model = model
        self._table = UR_DH[model]
        self._ik = UrInverse(self._table)
        self._lo = np.radians(np.asarray(limits.joint_min_deg, dtype=float))
        self._hi = np.radians(np.asarray(limits.joint_max_deg, dtype=float))
        self._wrist = math.sin(math.radians(limits.wrist_singularity_margin_deg))
        self._elbow = math.sin(math.radians(limits.elbow_singularity_margin_deg))
        self._shoulder_mm = limits.shoulder_singularity_margin_mm
        self._limits = limits
        self._tcp_memo: tuple[bytes, Matrix4] | None = None

    def T_tcp_flange(self, at: ArmAt) -> Matrix4:
        """The TCP the arm is using, as the nominal kinematics see it: where its joints put
        the flange against where it reports the TCP (one packet of the controller's)."""
        q = np.asarray(at.joints_rad, dtype=float).reshape(6)
        T = np.asarray(at.T_base_tcp, dtype=float)
        key = q.tobytes() + T.tobytes()
        memo = self._tcp_memo
        if memo is not None and memo[0] == key:
            return memo[1]
        out = invert_T(T) @ forward(self._table, q)
        self._tcp_memo = (key, out)
        return out

    # -- straight moves ------------------------------------------------------------------------
    def check_path(self, path: Sequence[Matrix4], what: str, at: ArmAt) -> Joints:
        """Every pose of a sampled straight path in the configuration the arm at ``at`` is
        in; returns the joints along it (N x 6). LimitError ``unreachable`` naming the first
        pose that fails and why."""
        q0 = np.asarray(at.joints_rad, dtype=float).reshape(6)
        P = np.asarray(path, dtype=float).reshape(-1, 4, 4) @ self.T_tcp_flange(at)
        f0 = self._ik.singular_factors(q0)
        first: LimitError | None = None
        for branch in _branches_near(f0):
            sols = self._ik.solve(P, branch, q0[5])
            failure, q = self._path_failure(sols, P, q0, f0)
            if failure is None:
                return q
            k, reason = failure
            err = LimitError(ErrorCode.unreachable, _message(what, path, k, reason))
            first = err if first is None else first
        assert first is not None
        raise first

    def _continued(self, q_raw: Joints, q0: Joints) -> Joints:
        return unwrap_from(wrap_near(q_raw[0], q0), q_raw)

    def _path_failure(self, sols: Solutions, P: NDArray[np.float64], q0: Joints,
                      f0: tuple[float, float, float]) -> tuple[tuple[int, str] | None, Joints]:
        """The first failing sample and why (None: none fails), and the joints along the
        path up to where a solution exists."""
        n = len(sols.exists)
        fails: list[tuple[int, str]] = []
        missing = ~sols.exists
        if missing.any():
            k = int(np.argmax(missing))
            fails.append((k, self._why_missing(P[k])))
        ok = slice(0, int(np.argmax(missing)) if missing.any() else n)
        for factor, need, start, name in (
                (sols.shoulder_mm, self._shoulder_mm, f0[0], "shoulder"),
                (sols.sin_elbow, self._elbow, f0[1], "elbow"),
                (sols.sin_wrist, self._wrist, f0[2], "wrist")):
            floor = min(need, abs(start)) - 1e-9
            near = np.abs(factor[ok]) < floor
            if near.any():
                k = int(np.argmax(near))
                fails.append((k, self._singular_text(name, float(factor[k]), need)))
        q = self._continued(sols.q_rad[ok], q0)
        if len(q) > 1:
            jump = np.abs(np.diff(q, axis=0)) > math.radians(MAX_JOINT_STEP_DEG)
            if jump.any():
                i, j = (int(v) for v in np.unravel_index(int(np.argmax(jump)), jump.shape))
                fails.append((i + 1, f"the {JOINT_NAMES[j]} joint would turn "
                              f"{math.degrees(abs(q[i + 1, j] - q[i, j])):.0f} deg at once: the "
                              "arm would pass through a singularity into another configuration"))
        lo, hi = np.minimum(self._lo, q0), np.maximum(self._hi, q0)
        out = (q < lo) | (q > hi)
        if out.any():
            i, j = (int(v) for v in np.unravel_index(int(np.argmax(out)), out.shape))
            fails.append((i, self._limit_text(j, float(q[i, j]))))
        return (min(fails, key=lambda f: f[0]) if fails else None), q

    def _why_missing(self, T_flange: Matrix4) -> str:
        every = self._ik.solve_all(T_flange)
        if every.exists.any():
            return ("reachable only in another arm configuration (shoulder, elbow or wrist "
                    "flipped), which a straight move cannot change to")
        return self._geometry_text(every)

    def _geometry_text(self, every: Solutions) -> str:
        inside = float(np.max(every.inside_shoulder_mm))
        if inside > 0:
            return (f"the wrist centre would be {inside:.0f} mm too close to the base axis "
                    f"(no pose within {abs(self._table.d_mm[3]):.0f} mm of it)")
        excess = float(np.min(every.reach_excess_mm))
        if excess > 0:
            return (f"out of reach by {excess:.0f} mm (the {_model_name(self.model)}'s upper arm "
                    f"and forearm span {self._ik.reach_mm:.0f} mm from the shoulder joint to "
                    "the wrist)")
        return "no wrist orientation gives the tool that orientation there"

    def _singular_text(self, name: str, factor: float, need: float) -> str:
        if name == "shoulder":
            return (f"the shoulder singularity: the wrist centre {abs(factor):.0f} mm from "
                    f"the base joint's axis (margin {need:g} mm)")
        joint = "wrist 2" if name == "wrist" else "elbow"
        margin = (self._limits.wrist_singularity_margin_deg if name == "wrist"
                  else self._limits.elbow_singularity_margin_deg)
        off = math.degrees(math.asin(min(1.0, abs(factor))))
        return (f"the {name} singularity: the {joint} joint {off:.1f} deg from 0/180 deg "
                f"(margin {margin:g} deg)")

    def _limit_text(self, j: int, q: float) -> str:
        return (f"the {JOINT_NAMES[j]} joint would reach {math.degrees(q):.0f} deg, outside "
                f"its range {math.degrees(self._lo[j]):g}..{math.degrees(self._hi[j]):g} deg")

    # -- joint moves ---------------------------------------------------------------------------
    def joints_for(self, T_base_tcp: Matrix4, what: str, at: ArmAt) -> Joints:
        """The joints a joint move from ``at`` to the pose takes: of the solutions inside the
        joint range and the margins, the one nearest the joints it starts from (LimitError
        ``unreachable`` when there is none, with why for the nearest one)."""
        q0 = np.asarray(at.joints_rad, dtype=float).reshape(6)
        T = np.asarray(T_base_tcp, dtype=float)
        every = self._ik.solve_all(T @ self.T_tcp_flange(at), float(q0[5]))
        best: tuple[float, Joints] | None = None
        nearest: tuple[float, str] | None = None
        for k in np.flatnonzero(every.exists):
            q, why = self._in_range(every.q_rad[k], q0)
            for factor, need, name in ((every.shoulder_mm[k], self._shoulder_mm, "shoulder"),
                                       (every.sin_elbow[k], self._elbow, "elbow"),
                                       (every.sin_wrist[k], self._wrist, "wrist")):
                if why is None and abs(factor) < need:
                    why = self._singular_text(name, float(factor), need)
            dist = float(np.max(np.abs(q - q0)))
            if why is None and (best is None or dist < best[0]):
                best = (dist, q)
            elif why is not None and (nearest is None or dist < nearest[0]):
                nearest = (dist, why)
        if best is not None:
            return best[1]
        reason = nearest[1] if nearest is not None else self._geometry_text(every)
        raise LimitError(ErrorCode.unreachable, _message(what, [T], 0, reason))

    def _in_range(self, q_raw: Joints, q0: Joints) -> tuple[Joints, str | None]:
        """Per joint, the 2*pi-equivalent inside the range nearest ``q0``."""
        q = wrap_near(q_raw, q0)
        for j in range(6):
            options = [q[j] + k * 2 * math.pi for k in (-1, 0, 1)]
            inside = [v for v in options if self._lo[j] <= v <= self._hi[j]]
            if not inside:
                return q, self._limit_text(j, float(q[j]))
            q[j] = min(inside, key=lambda v: abs(v - q0[j]))
        return q, None

    def joint_path(self, q_from: Joints, q_to: Joints, at: ArmAt, step_deg: float
                   ) -> list[Matrix4]:
        """TCP poses along a joint move (a line in joint space) by the nominal kinematics,
        with the TCP the arm at ``at`` uses, ``step_deg`` apart in the joint that turns most."""
        T_flange_tcp = invert_T(self.T_tcp_flange(at))
        n = max(2, int(np.ceil(np.degrees(np.max(np.abs(q_to - q_from))) / step_deg)) + 1)
        return [forward(self._table, q_from + u * (q_to - q_from)) @ T_flange_tcp
                for u in np.linspace(0.0, 1.0, n)]

    def check_joints(self, q_rad: Joints, what: str, at: ArmAt) -> None:
        """A joint move's target inside the joint range (a joint move is a line in joint
        space, so its ends bound it); one from outside may only come back towards it."""
        q = np.asarray(q_rad, dtype=float).reshape(6)
        q0 = np.asarray(at.joints_rad, dtype=float).reshape(6)
        lo, hi = np.minimum(self._lo, q0), np.maximum(self._hi, q0)
        out = (q < lo) | (q > hi)
        if out.any():
            j = int(np.argmax(out))
            raise LimitError(ErrorCode.unreachable, f"the {what} is unreachable: "
                             f"{self._limit_text(j, float(q[j]))}")


@dataclass(frozen=True)
class PhaseReach:
    """One pose of a sequence checked up front: the joints the arm will have there, or the
    refusal (its message names the phase)."""

    phase: str
    T_base_tcp: Matrix4
    joints_rad: Joints | None
    error: LimitError | None = None


@dataclass(frozen=True)
class ReachReport:
    """A sequence of poses checked before the first moves, in order, up to the first that
    fails (the ones after it start from a pose the arm will not reach: not checked)."""

    phases: tuple[PhaseReach, ...]

    @property
    def failed(self) -> PhaseReach | None:
        return next((p for p in self.phases if p.error is not None), None)

    @property
    def ok(self) -> bool:
        return self.failed is None

    def raise_if_unreachable(self) -> None:
        """The first phase's refusal (LimitError), if one failed."""
        failed = self.failed
        if failed is not None and failed.error is not None:
            raise failed.error


def _branches_near(f0: tuple[float, float, float]) -> list[Branch]:
    """The start's branch, and for a factor exactly on a singularity the other side too."""
    own = branch_of(f0)
    out = [own]
    for i, f in enumerate(f0):
        if abs(f) < _ON_SINGULARITY:
            out += [Branch(*(-v if j == i else v for j, v in enumerate(b))) for b in list(out)]
    return out


def _message(what: str, path: Sequence[Matrix4], k: int, reason: str) -> str:
    goal = np.round(np.asarray(path[-1])[:3, 3], 1).tolist()
    if len(path) == 1 or k == len(path) - 1:
        return f"the {what} at {goal} mm is unreachable: {reason}"
    at = np.round(np.asarray(path[k])[:3, 3], 1).tolist()
    return (f"the {what} at {goal} mm is unreachable along the straight path (at {at} mm): "
            f"{reason}")


def _model_name(model: str) -> str:
    """``ur5e`` as Universal Robots writes it: UR5e."""
    return model.upper()[:-1] + "e" if model.endswith("e") else model.upper()
