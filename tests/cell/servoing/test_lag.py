"""The track's lag watch: the pull-in is not a lag, an excursion ends the track only when it
lasts, and coming back on the goal starts the clock again."""

from __future__ import annotations

from cell.servoing.lag import LagWatch


def test_the_pull_in_from_far_away_is_not_judged() -> None:
    watch = LagWatch(25.0, 0.25)
    assert all(watch.over_for_s(t * 0.1, 300.0 - t) is None for t in range(40))


def test_an_excursion_ends_the_track_once_it_lasts_its_time() -> None:
    watch = LagWatch(25.0, 0.25)
    assert watch.over_for_s(0.0, 3.0) is None  # on the goal
    assert watch.over_for_s(1.0, 30.0) is None
    assert watch.over_for_s(1.2, 40.0) is None
    over = watch.over_for_s(1.3, 50.0)
    assert over is not None and abs(over - 0.3) < 1e-9


def test_back_on_the_goal_the_clock_starts_again() -> None:
    watch = LagWatch(25.0, 0.25)
    watch.over_for_s(0.0, 1.0)
    assert watch.over_for_s(1.0, 30.0) is None
    assert watch.over_for_s(1.2, 10.0) is None  # caught up
    assert watch.over_for_s(1.3, 30.0) is None
    assert watch.over_for_s(1.5, 30.0) is None
    over = watch.over_for_s(1.56, 30.0)
    assert over is not None and abs(over - 0.26) < 1e-9
