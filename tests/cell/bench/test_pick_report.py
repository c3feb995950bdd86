"""The pick bench's headlines count every attempt: a failed pick's cycle is infinitely long,
its part's error is what the truth measured, and a part never attempted is not picked."""

from __future__ import annotations

from typing import Any

from cell.bench.pick import _report, format_report, quantile

PHASES_S = {"locate": 0.3, "approach": 2.0, "grasp": 1.0, "verify": 0.3, "retract": 0.5,
            "place": 6.0}


def _ok(cycle_s: float, error_mm: float) -> dict[str, Any]:
    return {"attempt": True, "state": "succeeded", "code": None, "target": "six-dot",
            "place": "p", "cycle_s": cycle_s, "phases_s": PHASES_S, "error_mm": error_mm,
            "error_deg": 0.01, "error_vs_cell_goal_mm": error_mm}


MISSED = {"attempt": True, "state": "failed", "code": "grasp_missed", "target": "six-dot",
          "place": "p", "cycle_s": None, "error": "no object", "phases_s": {"locate": 0.3},
          "error_mm": 420.0, "error_deg": 3.0}
REFUSED = {"attempt": False, "state": "refused", "code": "target_not_visible", "cycle_s": None}


def test_quantiles_count_infinite_values_as_the_largest() -> None:
    assert quantile([1.0, 2.0, 3.0], 0.5) == 2.0
    assert quantile([1.0, 2.0, float("inf")], 0.5) == 2.0
    assert quantile([1.0, float("inf")], 0.95) is None
    assert quantile([], 0.5) is None


def test_a_failed_pick_counts_in_every_figure() -> None:
    rows = [_ok(10.0, 0.05), _ok(12.0, 0.1), MISSED, REFUSED]
    stops = [{"phase": "grasp", "ok": True}]
    r = _report(rows, 60.0, 4, [{"ok": True}], stops, "realistic", 0)
    assert r["picked_ratio"] == "2/4" and r["attempts"] == 3 and len(r["failures"]) == 1
    assert r["grasps_missed"] == 1
    # two successes, one failure, one part never attempted: the median is the worse success
    assert r["cycle_s_p50"] == 12.0 and r["cycle_s_p95"] is None
    assert r["place_error_mm_max"] is None  # the part never attempted has no error at all
    assert r["phases_s_p50"]["locate"] == 0.3 and r["phases_s_p50"]["place"] == 6.0
    assert r["parts_per_minute"] == 2.0
    met = r["targets_met"]
    assert not met["all_picked_and_placed"] and not met["place_within_0.3mm_0.1deg"]
    assert met["missed_grasp_all"] and met["stop_each_phase"]
    assert format_report(r).startswith("world realistic: picked and placed 2/4, 1 failed")


def test_every_part_placed_within_tolerance_meets_the_targets() -> None:
    r = _report([_ok(10.0, 0.05), _ok(11.0, 0.2)], 40.0, 2, [{"ok": True}],
                [{"phase": "place", "ok": True}], "ideal", 0)
    assert r["place_error_mm_max"] == 0.2 and r["place_error_mm_median"] == 0.05
    assert all(r["targets_met"].values())
