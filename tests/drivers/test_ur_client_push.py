"""What the ur_rtde child pushes to the adapter: every change, a standing arm's samples only
now and then, and the last held sample before the first that differs (the pose history then
knows when the arm started)."""

from __future__ import annotations

import dataclasses
import sys
import threading

import pytest

from drivers.ur.client_process import (
    QUIET_PUSH_S,
    RESTING_AFTER_S,
    STILL_DEADBAND_RAD,
    StateSample,
    _PushState,
    unchanged,
)
from drivers.ur.timer_slack import set_timer_slack, timer_slack, timer_slack_s


def sample(seq: int, x_m: float = 0.4, q0: float = 0.0, mode: int = 7) -> StateSample:
    return StateSample(connected=True, timestamp_s=seq * 0.008, tcp_pose=(x_m, 0.1, 0.3, 0, 3.1, 0),
                       q_rad=(q0, -1.5, 1.5, -1.5, -1.5, 0.0), qd_rad_s=(0.0,) * 6,
                       robot_mode=mode, safety_mode=1, safety_bits=1, runtime_state=2, seq=seq,
                       seen_s=seq * 0.008)


def test_a_standing_arm_is_pushed_only_every_quiet_period() -> None:
    ps = _PushState()
    sent = [s.seq for i in range(1, 126) for s in ps.offer(sample(i), i * 0.008)]
    # one second of packages at 125 Hz: the first, then one per quiet period
    assert sent[0] == 1
    assert 1 + int(1.0 / QUIET_PUSH_S) - 1 <= len(sent) <= 1 + int(1.0 / QUIET_PUSH_S) + 1


def test_the_held_sample_goes_out_before_the_first_change() -> None:
    ps = _PushState()
    assert [s.seq for s in ps.offer(sample(1), 0.008)] == [1]
    assert ps.offer(sample(2), 0.016) == []
    assert ps.offer(sample(3), 0.024) == []
    out = ps.offer(sample(4, x_m=0.401), 0.032)  # the arm moved 1 mm
    assert [s.seq for s in out] == [3, 4]
    # moving: every package goes out
    assert [s.seq for s in ps.offer(sample(5, x_m=0.402), 0.040)] == [5]


def test_the_pusher_rests_only_while_the_arm_stands_and_no_call_is_made() -> None:
    ps = _PushState()
    ps.offer(sample(1), 0.0)
    assert not ps.resting(0.1)
    for i in range(2, 100):  # standing
        ps.offer(sample(i), i * 0.008)
    assert ps.resting(RESTING_AFTER_S + 0.01)
    ps.offer(sample(100, x_m=0.401), 0.8)  # it moved
    assert not ps.resting(0.81)
    assert ps.resting(0.8 + RESTING_AFTER_S + 0.01)
    ps.pushed(sample(101, x_m=0.401), 2.0)  # a call was made: motion may follow
    assert not ps.resting(2.01)


def test_a_mode_change_is_pushed_at_once() -> None:
    ps = _PushState()
    ps.offer(sample(1), 0.008)
    assert [s.seq for s in ps.offer(sample(2, mode=3), 0.016)] == [2]


def test_encoder_noise_is_still_and_a_creep_adds_up() -> None:
    base = sample(1)
    assert unchanged(base, sample(2, q0=0.5 * STILL_DEADBAND_RAD))
    assert not unchanged(base, sample(2, q0=2.0 * STILL_DEADBAND_RAD))
    ps = _PushState()
    ps.offer(base, 0.0)
    sent = []
    for i in range(2, 10):  # creeping a third of the deadband per package
        sent += ps.offer(sample(i, q0=(i - 1) * STILL_DEADBAND_RAD / 3), i * 0.008)
    assert sent, "a creep beyond the deadband must be pushed"
    assert all(abs(s.q_rad[0] - base.q_rad[0]) > STILL_DEADBAND_RAD for s in sent[-1:])


def test_a_call_push_resets_the_hold() -> None:
    ps = _PushState()
    ps.offer(sample(1), 0.008)
    assert ps.offer(sample(2), 0.016) == []
    ps.pushed(sample(3), 0.020)
    moved = dataclasses.replace(sample(4), tcp_pose=(0.41, 0.1, 0.3, 0, 3.1, 0))
    assert [s.seq for s in ps.offer(moved, 0.024)] == [4]  # the held one is older than 3


def test_a_sample_request_takes_the_held_sample_out_first() -> None:
    ps = _PushState()
    ps.offer(sample(1), 0.008)
    assert ps.take_held(0.010) is None  # nothing held: nothing extra to send
    assert ps.offer(sample(2), 0.016) == []
    assert ps.offer(sample(3), 0.024) == []
    held = ps.take_held(0.025)
    assert held is not None and held.seq == 3  # the newest held, once
    assert ps.take_held(0.026) is None
    # it counts as sent: the next change goes out alone, the still one already did
    assert [s.seq for s in ps.offer(sample(4, x_m=0.401), 0.032)] == [4]


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="Linux timer slack")
def test_timer_slack_is_set_for_the_block_and_restored() -> None:
    before = timer_slack_s()
    assert before is not None
    with timer_slack(0.002):
        assert timer_slack_s() == pytest.approx(0.002)
        seen: list[float | None] = []
        t = threading.Thread(target=lambda: seen.append(timer_slack_s()))
        t.start()
        t.join()
        assert seen == [pytest.approx(0.002)]  # threads started in the block keep it
    assert timer_slack_s() == pytest.approx(before)
    assert set_timer_slack(before)
