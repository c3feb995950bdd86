"""``cell bench drift``, shortened to one clean check and one knock (a shift: a turn takes the
same path through the bench) in the ideal world: the reference recorded, the knock detected
and blamed on the camera, every key of the report there. Numbers beyond that are the
benchmark's to judge."""

from __future__ import annotations

from cell.bench.drift import format_report, run_bench_drift


def test_the_drift_bench_runs_and_reports_every_key() -> None:
    r = run_bench_drift(repeats=1, clean_checks=1, world="ideal", commissioned=False,
                        translations_mm=(1.0,), rotations_deg=())
    assert next(iter(r)) == "false_drifted"  # the least kind figure first
    assert r["false_drifted"] == "0/1" and r["clean_checks_failed"] == 0
    assert set(r["bumps"]) == {"translation_1mm"}
    for name, bump in r["bumps"].items():
        assert bump["detected"] == "1/1" and bump["failed"] == 0, (name, r["rows"])
        assert bump["true_tcp_error_mm_median"] is not None
    assert all(row.get("cause") == "camera" for row in r["rows"]), r["rows"]
    assert r["check_s_max"] is not None and set(r["targets_met"]) >= {"no_false_drifted",
                                                                        "check_within_15_s"}
    assert "false drifted" in format_report(r)
