"""``cell bench pick``, shortened: two parts (one of each layout) picked and placed in the
ideal world, one missed grasp, one stop; every key of the report there, and the outcomes the
simulator's truth gives in a world the cell's config describes exactly."""

from __future__ import annotations

from cell.bench.pick import PHASES, format_report, run_bench_pick

HEADLINE = ["picked_ratio", "failures", "cycle_s_p50", "cycle_s_p95", "place_error_mm_max",
            "place_error_deg_max", "place_error_mm_median", "place_error_deg_median",
            "phases_s_p50", "grasps_missed", "parts_per_minute"]
KEYS = {*HEADLINE, "placed_within_tolerance", "place_error_vs_cell_goal_mm_max",
        "missed_grasp", "stop_per_phase", "world", "seed", "parts", "picked", "attempts",
        "pick_section_s", "picks", "missed_grasp_runs", "stops", "targets_met",
        "commissioned", "commissioning", "load_average_before", "load_average_after",
        "home_failures"}


def test_the_pick_bench_picks_two_layouts_and_reports_every_key() -> None:
    r = run_bench_pick(parts=2, world="ideal", missed_runs=1, stop_phases=("grasp",))
    assert list(r)[:len(HEADLINE)] == HEADLINE  # the least kind figures first
    assert set(r) == KEYS
    assert set(r["targets_met"]) == {"all_picked_and_placed", "place_within_0.3mm_0.1deg",
                                     "missed_grasp_all", "stop_each_phase"}
    assert r["picked_ratio"] == "2/2" and not r["failures"], r["failures"]
    placed = [p for p in r["picks"] if p["state"] == "succeeded"]
    assert {p["target"] for p in placed} == {"six-dot", "five-dot"}  # both layouts taken
    assert len({p["place"] for p in placed}) == 2  # each to its own place pose
    for p in placed:
        assert p["grip"] == "held" and p["parts_moved"] == 1 and not p["held_after"]
        assert set(p["phases_s"]) == set(PHASES)
        assert p["cycle_s"] >= sum(p["phases_s"].values()) - 0.01  # the locate counted
    assert r["place_error_mm_max"] <= 0.3 and r["place_error_deg_max"] <= 0.1
    assert 0 < r["cycle_s_p50"] <= r["cycle_s_p95"]
    assert all(r["phases_s_p50"][ph] is not None for ph in PHASES)
    assert r["parts_per_minute"] > 0 and r["grasps_missed"] == 0
    run = r["missed_grasp_runs"][0]
    assert r["missed_grasp"] == "1/1", run
    assert run["code"] == "grasp_missed" and run["gripper_open"] and not run["held"]
    assert run["parts_moved_max_mm"] < 1e-3 and run["retracted_mm"] > 70.0
    assert r["stop_per_phase"] == {"grasp": True}, r["stops"]
    assert r["stops"][0]["state"] == "cancelled" and r["stops"][0]["arm_drift_mm"] < 0.01
    assert all(r["targets_met"].values()), r["targets_met"]
    text = format_report(r)
    assert text.startswith("world ideal: picked and placed 2/2") and "cycle time p50" in text
