"""What a motion command may see of the arm while it advances one control cycle.

Commands (:mod:`fakes.ur_sim.commands`) compute the next joint state from the present one; the
engine owns that state, the lock and the safety checks. Handing each step a frozen view of just
the state it needs keeps the dependency one way (the engine builds a context, commands read it)
and makes a command a function of what it is given, not of the engine's internals.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol

from numpy.typing import ArrayLike

from fakes.ur_sim.state import SimLimits, Vec


class ArmKinematics(Protocol):
    """The read-only kinematics a command uses (TCP offset included); the engine alone
    changes the TCP, and never while a command runs."""

    def forward_tcp(self, q_rad: ArrayLike) -> Vec: ...

    def jacobian_tcp(self, q_rad: ArrayLike) -> Vec: ...

    def inverse_tcp(self, T_base_tcp: ArrayLike, q_near: ArrayLike) -> Vec: ...

    def inverse_tcp_local(self, T_base_tcp: ArrayLike, q_seed: ArrayLike,
                          q_guess: ArrayLike | None = None, tol_mm: float = 1e-6) -> Vec: ...


@dataclass(frozen=True, slots=True)
class StepContext:
    """The arm at the start of a control cycle, as the command stepping it sees it.

    ``q`` and ``qd`` are the engine's present arrays, not copies (this runs at 500 Hz): a
    command reads them and returns new arrays in its :class:`~fakes.ur_sim.commands.Step`.
    """

    q: Vec  # joint positions (rad)
    qd: Vec  # joint velocities (rad/s)
    speed_fraction: float  # the speed slider (0..1): profiled moves run slower in time
    kin: ArmKinematics
    limits: SimLimits
