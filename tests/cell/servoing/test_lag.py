"""The track's lag watch: the pull-in and the catch-up are not a lag, a lag ends the track when
its RMS over the window is over the limit, swinging about the limit included, and a brief
excursion does not."""

from __future__ import annotations

from cell.servoing.lag import LagWatch


def test_the_pull_in_from_far_away_is_not_judged() -> None:
    watch = LagWatch(25.0, 0.25)
    assert all(watch.over_for_s(t * 0.1, 300.0 - t) is None for t in range(40))


def test_a_lag_ends_the_track_once_its_window_is_over_the_limit() -> None:
    watch = LagWatch(25.0, 0.25)
    assert watch.over_for_s(0.0, 3.0) is None  # on the goal
    watch.over_for_s(0.25, 3.0)  # a whole window on the goal: it follows
    assert watch.over_for_s(1.0, 20.0) is None  # the window: 3 mm held until now
    assert watch.over_for_s(1.2, 40.0) is None  # 0.05 s of 3 mm and 0.2 s of 20 mm: 17.9
    lag = watch.over_for_s(1.3, 50.0)  # 0.15 s of 20 mm and 0.1 s of 40 mm: 29.7
    assert lag is not None and abs(lag.rms_mm ** 2 - (0.15 * 20 ** 2 + 0.1 * 40 ** 2) / 0.25) \
        < 1e-6 and lag.window_s == 0.25


def test_a_brief_excursion_does_not_end_the_track() -> None:
    watch = LagWatch(25.0, 0.25)
    watch.over_for_s(0.0, 1.0)
    assert all(watch.over_for_s(1.0 + 0.033 * k, 2.0) is None for k in range(10))
    assert watch.over_for_s(1.33, 40.0) is None  # one frame far off
    assert watch.over_for_s(1.36, 2.0) is None  # back: 0.03 s of 40 mm is 13.9 mm RMS
    assert all(watch.over_for_s(1.39 + 0.033 * k, 2.0) is None for k in range(10))


def test_swinging_about_the_limit_ends_the_track() -> None:
    """A starved loop swinging about a lagging goal crosses under the limit now and then: each
    crossing used to start the clock again."""
    watch = LagWatch(10.0, 0.25)
    watch.over_for_s(0.0, 1.0)
    errors = [5.0, 30.0, 40.0, 20.0] * 10  # under the limit every fourth frame
    ended = [watch.over_for_s(0.05 * (k + 1), e) for k, e in enumerate(errors)]
    first = next(k for k, lag in enumerate(ended) if lag is not None)
    assert 0.05 * (first + 1) <= 2.05 and ended[first] is not None  # the catch-up allowed
    assert ended[first].rms_mm > 10.0
