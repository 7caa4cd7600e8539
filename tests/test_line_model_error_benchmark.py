"""``benchmarks/line_model_error.py``: the summary over seeds, on constructed rows."""

from __future__ import annotations

import pytest
from scipy.stats import chi2

from tests.scripts import load_benchmark


def test_summary_pools_the_seeds_per_terms_and_estimator() -> None:
    bench = load_benchmark("line_model_error")
    rows = [
        {
            "log": "x",
            "terms": t,
            "estimator": e,
            "rmse_m": r,
            "nees_mean": n,
            "nees_effective_samples": 50.0,
        }
        for t, e, r, n in [
            ("correlated", "batch", 0.1, 3.0),
            ("correlated", "batch", 0.3, 5.0),
            ("profile", "batch", 0.2, 9.0),
        ]
    ]
    out = bench.summary(rows)
    # Sources in SOURCES order: the profile's first.
    assert [(s["terms"], s["seeds"]) for s in out] == [("profile", 1), ("correlated", 2)]
    corr = out[1]
    assert corr["anees"] == pytest.approx(4.0)
    assert corr["rmse_median_m"] == pytest.approx(0.2)
    # 3 dof per effective sample, 100 of them: the χ² region of their mean.
    assert corr["interval"][0] == pytest.approx(chi2.ppf(0.025, 300) / 100)
    assert corr["interval"][1] == pytest.approx(chi2.ppf(0.975, 300) / 100)
