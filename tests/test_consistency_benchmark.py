"""``benchmarks/consistency_loop600.py`` on a short synthetic run (loop600 itself takes
minutes a seed; the statistics it uses are tested in ``test_nees_statistics.py``)."""

from __future__ import annotations

import dataclasses
import json
from types import ModuleType

import numpy as np
import pytest

from tests.scripts import load_benchmark
from tests.synthetic import synthetic_log


@pytest.fixture(scope="module")
def bench() -> ModuleType:
    return load_benchmark("consistency_loop600")


def test_a_row_and_its_summary(bench: ModuleType) -> None:
    log = synthetic_log(steps=200, seed=1)
    row = bench.log_row(log, 1, 20, 2000)
    json.dumps(row)  # plain JSON types only
    draws = row["consistent_smoother_draws"]
    # Errors drawn from the smoother's own covariance are consistent by construction:
    # on average 95 % of the steps within the χ² bound (2,000 draws of 9 steps each).
    assert draws["fraction_within_mean"] == pytest.approx(0.95, abs=0.01)
    for key in ("p_fraction_within_below_0_9", "p_max_position_error_above_0_15"):
        assert 0.0 <= draws[key] <= 1.0
    assert np.isfinite(row["batch"]["mean_nees"])
    lo, hi = row["batch"]["model_interval_95"]
    assert lo < 3.0 < hi
    assert row["anchor"]["ekf"] is not None
    assert 0.0 <= row["anchor"]["ekf"]["p_consistent_anchor_misses"] <= 1.0
    # Same seed, same row.
    assert bench.log_row(log, 1, 20, 2000) == row
    out = bench.summary([row, row], 20)
    p = 1.0 - draws["p_fraction_within_below_0_9"]
    assert out["p_consistent_smoother_passes_nees_on_every_seed"] == pytest.approx(p * p, abs=1e-3)
    assert out["anchor_seeds"] == 2


def test_a_log_without_truth_is_refused(bench: ModuleType) -> None:
    log = synthetic_log(steps=30, seed=0)
    with pytest.raises(ValueError, match="no true poses"):
        bench.log_row(dataclasses.replace(log, true_poses=None), 0, 5, 10)
