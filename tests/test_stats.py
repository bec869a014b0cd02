import numpy as np
import pytest

from pobax.eval import auc, bootstrap_ci, final_value, iqm


def test_bootstrap_ci_of_normal_sample_matches_t_interval():
    rng = np.random.default_rng(0)
    x = rng.normal(3.0, 1.0, size=200)
    mean, lo, hi = bootstrap_ci(x, n_resamples=20_000)
    se = x.std(ddof=1) / np.sqrt(x.size)
    assert mean == pytest.approx(x.mean())
    assert lo == pytest.approx(mean - 1.96 * se, abs=0.03)
    assert hi == pytest.approx(mean + 1.96 * se, abs=0.03)


def test_bootstrap_ci_edge_cases():
    mean, lo, hi = bootstrap_ci([2.0])  # one seed: no interval, not a zero-width one
    assert mean == 2.0 and np.isnan(lo) and np.isnan(hi)
    assert bootstrap_ci([1.0, np.nan, 1.0]) == (1.0, 1.0, 1.0)
    assert all(np.isnan(bootstrap_ci([np.nan])))


def test_iqm_known_values():
    assert iqm([1, 2, 3, 4, 5, 6, 7, 8]) == pytest.approx(4.5)  # mean of 3..6
    assert iqm([100, 1, 2, 3]) == pytest.approx(2.5)  # drops 1 and 100
    assert iqm([0, 0, 0, 0, 0, 0, 0, 1000]) == 0.0


def test_auc_and_final_value():
    curve = np.array([0.0, 1.0, 2.0, np.nan, 3.0])
    assert auc(curve) == pytest.approx(1.5)
    assert final_value(np.arange(100.0)) == pytest.approx(np.mean(np.arange(90.0, 100.0)))
    assert final_value([1.0, np.nan]) == 1.0


def test_a_one_seed_interval_reads_nan_in_every_report_even_after_json(tmp_path):
    """One seed has no interval (NaN bounds, written to JSON as null): the gap report and the Markdown table still
    print, with "nan" where the bound would be."""
    import json

    from pobax.eval import format_gap
    from pobax.eval._files import write_json
    from pobax.eval._report import _ci

    mean, lo, hi = bootstrap_ci([1.5])
    block = {"mean": mean, "ci_low": lo, "ci_high": hi}
    report = {"env": "tmaze_10", "metric": "disc_return", "figure": "gap.png", "reference": {},
              "gap": {"holds": None, "reasons": ["one seed"]},
              "agents": [{"agent": "floor", "disc_return": block, "return": block, "lr": 2.5e-4, "lambda0": 0.9}]}
    write_json(tmp_path / "gap.json", report)
    read = json.loads((tmp_path / "gap.json").read_text())
    assert read["agents"][0]["return"]["ci_low"] is None
    row = format_gap(read).splitlines()[2]
    assert row.replace(" ", "").startswith("floor1.500[nan,nan]1.500[nan,nan]")
    assert _ci(read["agents"][0]["return"]) == "1.5 [nan, nan]"


def test_infinite_values_give_the_infinity_and_no_interval_without_warnings():
    """A return summed past float32's range is inf: its mean was inf with NaN bounds after numpy's "invalid value"
    warnings (inf - inf), and large values printed as 38-digit fixed-point numbers."""
    import warnings

    from pobax.eval._stats import format_ci, mean_ci

    with warnings.catch_warnings():
        warnings.simplefilter("error")
        for values, mean in [([np.inf, np.inf, 1.0], np.inf), ([-np.inf, 2.0], -np.inf), ([np.inf, -np.inf], np.nan),
                             ([np.inf] * 12, np.inf)]:
            block = mean_ci(values)
            assert np.isnan(block["ci_low"]) and np.isnan(block["ci_high"]), values
            assert (np.isnan(block["mean"]) if np.isnan(mean) else block["mean"] == mean), values
    assert format_ci({"mean": 2e37, "ci_low": -1.5e37, "ci_high": np.inf}) == "2e+37 [-1.5e+37, inf]"
    assert format_ci({"mean": 12.25, "ci_low": 9999999.0, "ci_high": None}) == "12.250 [9999999.000, nan]"
