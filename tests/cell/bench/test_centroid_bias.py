"""``cell bench bias``: the simulated camera's dot centre bias, from a short sweep."""

from __future__ import annotations

from cell.bench.centroid_bias import format_report, run_bench_bias


def test_the_bias_of_the_simulated_dots_is_a_few_thousandths_of_a_pixel() -> None:
    r = run_bench_bias(frames=2, steps=5)
    assert r["frames_missing_a_dot"] == 0
    assert set(r["sweeps"]) == {"x", "y"}
    # the continuous renderer's dots: well under the 0.01 px the quantised ones carried,
    # noise of two frames included; not zero (the pixel grid and the grey levels are there)
    assert 0.0005 < r["bias_px_rms"] < 0.008, r
    assert r["bias_px_worst"] >= r["bias_px_rms"]
    assert "px RMS per image coordinate" in format_report(r)
