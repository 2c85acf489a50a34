"""examples/bench_freq.py: the three L_freq paths it times agree, and its ratios are against the
reference timed in the same call."""
from example_fixtures import load_example


def test_bench_reports_agreeing_paths_and_ratios_to_the_reference():
    r = load_example("bench_freq.py").bench(9, 12, repeats=2)
    assert r["size"] == "9x12"
    assert r["value_rel_err"] < 1e-12 and r["grad_rel_err"] < 1e-12
    assert abs(r["fast_ratio"] * r["reference_ms"] - r["fast_ms"]) <= 1e-9 * r["fast_ms"]
    assert r["fast_cached_target_ms"] > 0 and r["reference_ms"] > 0
