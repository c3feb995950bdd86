"""The approach bench's headlines count every run: failures are in the ratios and medians."""

from __future__ import annotations

from typing import Any

from cell.bench.approach import _median, _report, format_report


def _row(mode: str, state: str, time_s: float | None, error_mm: float | None) -> dict[str, Any]:
    return {"placement": 0, "mode": mode, "state": state, "time_s": time_s,
            "error_mm": error_mm, "error_deg": None if error_mm is None else 0.1}


ROWS = [_row("servo", "succeeded", 2.0, 0.1), _row("servo", "succeeded", 2.2, 0.2),
        _row("servo", "failed", 1.0, 40.0), _row("look_and_move", "succeeded", 7.0, 0.05),
        _row("look_and_move", "failed", None, None)]


def test_a_failure_counts_in_every_median() -> None:
    # the failed run's time is infinitely bad, its measured final error counts as it is
    assert _median(ROWS, "servo", "time_s") == 2.2
    assert _median(ROWS, "servo", "error_mm") == 0.2
    # one success and one failure without a time: the median is the failure's, unknown
    assert _median(ROWS, "look_and_move", "time_s") is None


def test_the_report_leads_with_the_least_kind_figures() -> None:
    lost = {"cover_to_still_ms": 180.0, "declared_to_still_ms": 20.0, "job_stopped_in_ms": 15.0,
            "truth_stop_ms": 80.0}
    tracks = [{"speed_mm_s": 100.0, "rms_error_mm": 1.2}, {"speed_mm_s": 150.0,
                                                          "rms_error_mm": 3.0}]
    r = _report(ROWS, tracks, lost, 3, 0, 0.1, "realistic")
    assert list(r)[:5] == ["world", "servo_success_ratio", "look_and_move_success_ratio",
                           "lost_target_cover_to_still_ms", "track_rms_error_mm"]
    assert (r["servo_success_ratio"], r["look_and_move_success_ratio"]) == ("2/3", "1/2")
    met = r["targets_met"]
    assert not met["every_approach_succeeded"] and met["lost_target_cover_to_still_le_250ms"]
    assert met["track_100_le_1.5mm"] and not met["track_150_le_2.5mm"]
    text = format_report(r)
    assert text.startswith("world realistic: servo succeeded 2/3, look-and-move 1/2; lens "
                           "covered -> arm still 180 ms")


def test_the_report_says_how_the_cell_was_commissioned_and_where_a_stop_went() -> None:
    lost = {"cover_to_still_ms": None, "cover_to_still_measured_ms": 90.0, "valid": False,
            "last_pose_exposure_ms": -30.0, "cover_to_declared_ms": 120.0,
            "arm_speed_at_cover_mm_s": 2.0, "declared_to_still_ms": -30.0,
            "job_stopped_in_ms": 15.0, "truth_stop_ms": -10.0}
    r = _report(ROWS, [], lost, 3, 0, 0.1, "realistic")
    assert r["lost_target_cover_to_still_ms"] is None  # the arm was not following: no figure
    r["commissioning"] = {
        "intrinsics": {"views": 14, "rms_px": 0.01, "coverage": 0.37,
                       "camera": {"fx": 806.3, "fy": 805.5, "cx": 643.0, "cy": 397.0},
                       "truth": {"fx": 806.4, "fy": 805.6, "cx": 643.0, "cy": 397.0}},
        "hand_eye": {"views": 12, "routine_s": 50.0, "verdict_consistent": False,
                     "applied": False, "mount_error_before_mm": 2.08,
                     "mount_error_before_deg": 0.447, "mount_error_after_mm": 2.08,
                     "mount_error_after_deg": 0.447,
                     "methods_vs_truth": {"tsai": {"mm": 0.31, "deg": 0.037}}}}
    text = format_report(r)
    assert "NOT counted" in text and "last frame showing the target exposed at -30" in text
    assert "intrinsics: 14 board views" in text and "INCONSISTENT, Apply refused" in text
