"""The simulated arm's motion commands step from a read-only view of the arm, no engine.

Each command is driven here cycle by cycle the way the engine's thread drives it, feeding back
the joints it returned, so the outcomes are the commands' own physics.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from fakes.ur_sim.commands import Brake, Command, MoveJ, MoveL, SpeedJ
from fakes.ur_sim.kinematics import UR5eKinematics
from fakes.ur_sim.profiles import BlendedLinearPath, JointProfile, LinearProfile
from fakes.ur_sim.state import CYCLE_S, HOME_Q_RAD, SimLimits
from fakes.ur_sim.step_context import StepContext

HOME = np.array(HOME_Q_RAD)


def _run(cmd: Command, ctx: StepContext, max_cycles: int = 20000) -> tuple[StepContext, int]:
    """Step ``cmd`` to its end; returns the last context and the cycles it took."""
    for n in range(1, max_cycles + 1):
        out = cmd.step(ctx, n * CYCLE_S, CYCLE_S)
        ctx = dataclasses.replace(ctx, q=out.q, qd=out.qd)
        if out.done:
            return ctx, n
    raise AssertionError(f"{cmd.name} did not finish in {max_cycles} cycles")


def _ctx(speed_fraction: float = 1.0) -> StepContext:
    return StepContext(HOME.copy(), np.zeros(6), speed_fraction, UR5eKinematics(), SimLimits())


def test_context_is_read_only() -> None:
    with pytest.raises(dataclasses.FrozenInstanceError):
        _ctx().speed_fraction = 0.5  # type: ignore[misc]


def test_move_j_lands_in_profile_time_stretched_by_the_speed_slider() -> None:
    q1 = HOME + np.array([0.5, -0.2, 0.3, 0.0, 0.1, -0.4])
    profile = JointProfile(HOME, q1, 1.0, 2.0)
    end, cycles = _run(MoveJ(1, "movej", profile), _ctx())
    assert np.allclose(end.q, q1, atol=1e-12)
    assert cycles * CYCLE_S == pytest.approx(profile.duration_s, abs=CYCLE_S)
    _, slow_cycles = _run(MoveJ(2, "movej", profile), _ctx(0.5))
    assert slow_cycles * CYCLE_S == pytest.approx(2 * profile.duration_s, abs=CYCLE_S)


def test_move_l_keeps_the_tcp_on_the_line() -> None:
    ctx = _ctx()
    T0 = ctx.kin.forward_tcp(ctx.q)
    T1 = T0.copy()
    T1[:3, 3] += [100.0, 50.0, -80.0]
    path = BlendedLinearPath([LinearProfile(T0, T1, 200.0, 1000.0, 0.2, 1.0)], [])
    cmd = MoveL(1, "movel", path)
    worst_mm = 0.0
    direction = (T1[:3, 3] - T0[:3, 3]) / np.linalg.norm(T1[:3, 3] - T0[:3, 3])
    for n in range(1, 5000):
        out = cmd.step(ctx, n * CYCLE_S, CYCLE_S)
        ctx = dataclasses.replace(ctx, q=out.q, qd=out.qd)
        off = ctx.kin.forward_tcp(ctx.q)[:3, 3] - T0[:3, 3]
        worst_mm = max(worst_mm, float(np.linalg.norm(off - np.dot(off, direction) * direction)))
        if out.done:
            break
    assert out.done
    assert np.allclose(ctx.kin.forward_tcp(ctx.q), T1, atol=1e-6)
    assert worst_mm < 0.01


def test_speed_j_ramps_then_brakes_to_rest() -> None:
    target = np.array([0.4, 0.0, 0.0, 0.0, 0.0, -0.2])
    cmd = SpeedJ(1, np.zeros(6), target, 2.0, expire_at=0.5)
    ctx, cycles = _run(cmd, _ctx())
    assert not np.any(ctx.qd)
    # 0.2 s up to 0.4 rad/s, 0.3 s at speed, 0.2 s down: 0.04 + 0.12 + 0.04 rad on joint 0
    assert ctx.q[0] - HOME[0] == pytest.approx(0.2, abs=2e-3)
    assert cycles * CYCLE_S == pytest.approx(0.7, abs=2 * CYCLE_S)


def test_brake_stops_every_joint_at_the_same_instant() -> None:
    qd0 = np.array([1.0, -0.5, 0.25, 0.0, 0.0, 0.0])
    brake = Brake(0, "stop", HOME, qd0, decel=10.0)
    ctx, cycles = _run(brake, dataclasses.replace(_ctx(), qd=qd0))
    assert np.allclose(ctx.q, HOME + 0.5 * 0.1 * qd0)
    assert not np.any(ctx.qd)
    assert cycles * CYCLE_S == pytest.approx(0.1, abs=CYCLE_S)
