"""``EKFConfig.local_map_heading_sigma_rad``: a local map is also joined once its
odometry has accumulated a heading σ above the bound (dead reckoning)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from ekf_reference import EKFConfig, run_ekf
from tests.synthetic import synthetic_log


def _expected_joins(heading_var: np.ndarray, steps: int, bound: float | None) -> int:
    """Joins of a run whose step ``k > 0`` predicts an increment of heading variance
    ``heading_var[k]``: a local map ends after ``steps`` steps or once the variance it
    has summed exceeds ``bound²``; the last step always joins."""
    n = heading_var.size
    joins, start, acc = 0, 0, 0.0
    for k in range(n):
        if k > 0:
            acc += float(heading_var[k])
        full = k + 1 - start >= steps or (bound is not None and acc > bound * bound)
        if k == n - 1 or full:
            joins, start, acc = joins + 1, k + 1, 0.0
    return joins


@pytest.mark.parametrize("bound", [None, 0.004, 0.01])
def test_local_maps_end_where_the_odometry_heading_sigma_passes_the_bound(
    bound: float | None,
) -> None:
    log = synthetic_log(steps=120, seed=3)
    var = log.odometry_cov[:, 2, 2]
    expected = _expected_joins(var, 40, bound)
    res = run_ekf(log, EKFConfig(local_map_heading_sigma_rad=bound), fusion=False)
    assert res.details.joins == expected
    # The cases differ: 3 joins by steps alone (120 / 40), more with a bound.
    # synthetic_log's heading σ per step is 0.002 rad: 0.004 ends a map every 5
    # steps (variance 5 × 4e-6 > 1.6e-5), 0.01 every 26 (26 × 4e-6 > 1e-4).
    assert np.allclose(var[1:], 0.002**2)
    assert expected == {None: 3, 0.004: 24, 0.01: 5}[bound]


def test_paper_preset_has_no_heading_bound() -> None:
    assert EKFConfig.paper().local_map_heading_sigma_rad is None


@pytest.mark.parametrize("bad", [0.0, -0.01, math.nan, math.inf, "0.1"])
def test_a_bad_heading_bound_is_refused(bad: object) -> None:
    with pytest.raises(ValueError, match="local_map_heading_sigma_rad"):
        EKFConfig(local_map_heading_sigma_rad=bad)  # type: ignore[arg-type]
