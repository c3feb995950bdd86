"""GuardedArm.servo_twist on the in-process simulated arm: every tick checked, refusals send
nothing, the arm's own watchdog stops it when ticks stop."""

from __future__ import annotations

import time
from collections.abc import Iterator
from dataclasses import replace

import numpy as np
import pytest

from cell.config.schema import LimitsConfig
from cell.errors import CellError
from cell.motion.guard import GuardedArm, servo_ahead
from drivers.arm import ArmState
from estimator.transforms import pose_distance
from fakes.sim_arm import SimArm
from fakes.ur_sim import SimLimits

FAST = SimLimits(power_on_s=0.05, brake_release_s=0.05, unlock_delay_s=0.5)


@pytest.fixture
def sim() -> Iterator[SimArm]:
    a = SimArm(q_rad=list(np.radians([0.0, -90.0, 90.0, -90.0, -90.0, 0.0])), limits=FAST)
    a.connect()
    a.power_on()
    yield a
    a.close()


def _guarded(sim: SimArm, z_max_mm: float | None = None) -> GuardedArm:
    z = sim.tcp_pose()[2, 3]
    limits = LimitsConfig(workspace_min_mm=(-900.0, -900.0, -100.0),
                          workspace_max_mm=(900.0, 900.0, z + 30.0 if z_max_mm is None
                                            else z_max_mm))
    return GuardedArm(sim, limits)


def _still(sim: SimArm, timeout_s: float = 3.0) -> None:
    deadline = time.monotonic() + timeout_s
    while sim.is_moving():
        assert time.monotonic() < deadline
        time.sleep(0.01)


def test_refusals_send_nothing(sim: SimArm) -> None:
    arm = _guarded(sim)
    T0 = sim.tcp_pose()
    with pytest.raises(CellError) as err:
        arm.servo_twist(np.array([10.0, 0, 0, 0, 0, 0]), 1000.0, 0.08)
    assert err.value.code == "no_motion_slot"
    with arm.slot.hold("servo"):
        cases = [
            (np.array([300.0, 0, 0, 0, 0, 0]), 1000.0, "speed_limit"),
            (np.array([0, 0, 0, 0, 0, np.radians(120.0)]), 1000.0, "speed_limit"),
            (np.array([5.0, 0, 0, 0, 0, 0]), 5000.0, "accel_limit"),
            (np.array([100.0, 0, 0, 0, 0, 0]), 1000.0, "accel_limit"),  # a jump from rest
            (np.array([np.nan, 0, 0, 0, 0, 0]), 1000.0, "invalid_request"),
        ]
        for twist, accel, code in cases:
            with pytest.raises(CellError) as err:
                arm.servo_twist(twist, accel, 0.08)
            assert err.value.code == code, (twist, err.value.message)
    assert not arm.commanded()
    time.sleep(0.1)
    assert pose_distance(T0, sim.tcp_pose())[0] < 1e-6


def _ramp_up_until_refused(arm: GuardedArm) -> CellError | None:
    """Servo ticks along +z, speeding up at 1000 mm/s^2 to 200 mm/s, until one is refused
    (the refusal), at most 400 ticks (None)."""
    v = 0.0
    for _ in range(400):
        v = min(v + 1000.0 * 0.008, 200.0)
        try:
            arm.servo_twist(np.array([0.0, 0.0, v, 0.0, 0.0, 0.0]), 1000.0, 0.08)
        except CellError as err:
            return err
        time.sleep(0.008)
    return None


def test_ramp_is_recorded_and_the_look_ahead_stops_it_before_the_box(sim: SimArm) -> None:
    """Ramping up towards the box's ceiling 30 mm above: ticks pass until the twist, held
    for the watchdog and then braked, would cross it; that one is refused, and the arm
    (stopped) stays inside."""
    arm = _guarded(sim)
    z_max = arm.limits.workspace_max_mm[2]
    with arm.slot.hold("servo"):
        refused = _ramp_up_until_refused(arm)
        arm.stop(1000.0)
    assert refused is not None and refused.code == "outside_envelope"
    _still(sim)
    assert sim.tcp_pose()[2, 3] <= z_max
    ticks = [c for c in arm.commanded() if c.kind == "servo"]
    assert len(ticks) > 3
    for c in ticks:
        assert c.T_base_tcp is not None and c.T_base_tcp[2, 3] <= z_max + 1e-6
        assert c.T_from is not None and c.velocity is not None
        ahead = servo_ahead(c.T_from, c.velocity, 1000.0, 0.08)
        assert np.allclose(ahead, c.T_base_tcp)


def test_the_arm_stops_by_itself_when_ticks_stop(sim: SimArm) -> None:
    arm = _guarded(sim, z_max_mm=900.0)
    with arm.slot.hold("servo"):
        v = 0.0
        for _ in range(10):
            v += 8.0
            arm.servo_twist(np.array([v, 0, 0, 0, 0, 0]), 1000.0, 0.08)
            time.sleep(0.008)
        t_last = time.monotonic()
        assert sim.is_moving()
        _still(sim)  # no stop was sent: the watchdog braked it
        assert time.monotonic() - t_last < 1.0


class _LateReadings:
    """The simulated arm, read ``lag_s`` late (as a loaded host gets its RTDE state): its
    state is the pose of ``lag_s`` ago, stamped with that time."""

    def __init__(self, sim: SimArm, lag_s: float) -> None:
        self._sim, self.lag_s = sim, lag_s

    def __getattr__(self, name: str) -> object:
        return getattr(self._sim, name)

    def state(self) -> ArmState:
        st = self._sim.state()
        taken_s = st.timestamp_s - self.lag_s
        return replace(st, T_base_tcp=self._sim.pose_at(taken_s), timestamp_s=taken_s)


def test_the_look_ahead_starts_where_the_arm_is_now_not_where_it_was_read(
        sim: SimArm) -> None:
    """Ramping towards the ceiling with every reading 40 ms old: the check moves the
    reading on by the last twist over its age, so the refused tick comes as early as with
    fresh readings, and the arm, left to its watchdog (no stop sent, as if the host
    stalled), stays inside."""
    late = _LateReadings(sim, 0.04)
    arm = GuardedArm(late, _guarded(sim).limits)  # type: ignore[arg-type]
    z_max = arm.limits.workspace_max_mm[2]
    with arm.slot.hold("servo"):
        refused = _ramp_up_until_refused(arm)
    assert refused is not None and refused.code == "outside_envelope"
    _still(sim)
    assert sim.tcp_pose()[2, 3] <= z_max
